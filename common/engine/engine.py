"""The engine: the primitives an algorithm's loop is written with, for rows of agents.

An algorithm (``common/algorithms/<name>.py``) holds the one loop of its local update over
θ rows [A, d]; the engine gives it, for any subset of rows at once:

- :meth:`Engine.sample`: B trajectories per row, drawn at each row's own θ from its own
  environment variant (keys: seed, agent, round, purpose, iteration, trajectory);
- :meth:`Engine.coefficients`: the run's estimator (REINFORCE or GPOMDP, baselines,
  discounting: ``common/estimators.py``, the one implementation) for those trajectories;
- :meth:`Engine.gradients`, :meth:`Engine.log_probs`, :meth:`Engine.trajectory_gradients`:
  the policy's score-function maths per row (``PolicyRows``);
- :meth:`Engine.finished`: the bookkeeping of an iteration (statistics, the device
  emulation's hook, cancellation).

Everything lives on ``algo.device``: torch on the CPU or on a GPU. Rows are placement-free:
what a row computes depends on its agent, round and θ alone.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

import torch

from fedhpg.common import estimators
from fedhpg.common.attacks import attack_of
from fedhpg.common.components import AgentProfile, agent_profile, planned_budget
from fedhpg.common.config import RunConfig
from fedhpg.common.engine.copies import make_copies
from fedhpg.common.engine.devices import check_device, deterministic_off_cpu
from fedhpg.common.engine.memory import (
    RoundPlan,
    StepBytes,
    memory_budget,
    packed_elements,
    plan_round,
)
from fedhpg.common.engine.policy_rows import PolicyRows, chunked
from fedhpg.common.engine.sampling import Faults, act_tiles_per_call, sample
from fedhpg.common.engine.trajectories import Trajectories
from fedhpg.common.randomness import Purpose, trajectory_keys
from fedhpg.common.staircase import ordered_sums
from fedhpg.common.types import EvaluationStats
from fedhpg.common.variants import discount, training_horizon
from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.device import DeviceFamily, device_family, put_distinct

if TYPE_CHECKING:
    from fedhpg.common.batched.backend import CompiledBackend


@contextmanager
def one_thread() -> Iterator[None]:
    """Run the enclosed maths on one CPU thread. Several threads would split reductions (a
    scatter-add's, a matrix product's) by the thread count, so the floats of an agent would
    depend on the process's thread setting: an agent process (one thread) and the in-process
    pool (as many as the machine) must compute the same θ."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@contextmanager
def engine_settings(device: torch.device) -> Iterator[None]:
    """What every use of the engine runs under: one CPU thread (:func:`one_thread`) and, off
    the CPU, torch's deterministic algorithms (:func:`deterministic_off_cpu`), so that an
    agent's floats depend neither on the process nor on its company; the caller's settings
    come back after."""
    with one_thread(), deterministic_off_cpu(device):
        yield


TILE = 64
"""Steps per tile of the policy's maths. Every per-row reduction over steps is made of
fixed-size tiles summed in order, so its floats never depend on the batch's shape (a matrix
product's blocking over a longer reduction would change the order of the additions)."""


@dataclass(frozen=True)
class _Tiles:
    """A batch's alive steps cut into tiles of :data:`TILE` steps of one group each."""

    obs: torch.Tensor
    """[tiles, TILE, *obs_shape] (zeros past a group's last step)."""
    act: torch.Tensor
    tile: torch.Tensor
    """Each alive step's tile."""
    slot: torch.Tensor
    """Its place in the tile."""
    flat: torch.Tensor
    """Its (t, n) as a flat index of [T, N]."""
    cell: torch.Tensor
    """Its cell of the batch's layout (where its coefficient is)."""
    tile_group: torch.Tensor
    """Each tile's group."""
    tile_start: torch.Tensor
    """Each group's first tile."""
    tiles_per_group: torch.Tensor


@dataclass
class RowWork:
    """What one iteration cost each row: what the device emulation prices."""

    rows: torch.Tensor
    """Positions of the rows that ran it."""
    iterations: torch.Tensor
    """Each one's iteration number (its own count of iterations this round)."""
    compute_s: torch.Tensor
    env_steps: torch.Tensor
    grad_steps: torch.Tensor


@dataclass
class Rows:
    """The agents one call trains, as rows: their θ̃ copies, budgets, discounts, horizons."""

    agents: list[int]
    theta: torch.Tensor
    """[A, d]: every row starts from θ̃."""
    budgets: dict[str, torch.Tensor]
    """Each budget field as [A] int64 (the configured budget, or the round's plan)."""
    round_index: int

    def budget(self, name: str) -> torch.Tensor:
        return self.budgets[name]

    @property
    def size(self) -> int:
        return len(self.agents)


@dataclass
class Tally:
    """Per-row totals of a round (``UpdateStats``), and its work per iteration."""

    trajectories: torch.Tensor
    env_steps: torch.Tensor
    return_sum: torch.Tensor
    compute_s: torch.Tensor
    clipped: torch.Tensor
    iterations: torch.Tensor
    sample_s: torch.Tensor
    """Each row's share of the CPU time spent sampling (the rest of ``compute_s`` went to
    its gradients and steps)."""
    algorithm: dict[str, torch.Tensor] = field(default_factory=dict)
    """Per-row algorithm statistics; NaN where a row has none."""
    work: list[RowWork] = field(default_factory=list)

    @classmethod
    def zeros(cls, rows: int) -> Tally:
        trajectories, env_steps, clipped, iterations = torch.zeros((4, rows), dtype=torch.int64)
        return_sum, compute_s, sample_s = torch.zeros((3, rows), dtype=torch.float64)
        return cls(trajectories, env_steps, return_sum, compute_s, clipped, iterations, sample_s)

    @classmethod
    def concatenated(cls, parts: Sequence[Tally]) -> Tally:
        """The tallies of consecutive chunks of a round's rows as one (its works' rows
        renumbered in the whole round)."""
        if len(parts) == 1:
            return parts[0]
        names = list(dict.fromkeys(name for part in parts for name in part.algorithm))

        def stat(part: Tally, name: str) -> torch.Tensor:
            values = part.algorithm.get(name)
            return values if values is not None else torch.full_like(part.sample_s, math.nan)

        starts = [0]
        for part in parts[:-1]:
            starts.append(starts[-1] + int(part.trajectories.shape[0]))
        return cls(
            **{
                name: torch.cat([getattr(p, name) for p in parts])
                for name in (f.name for f in fields(cls))
                if name not in ("algorithm", "work")
            },
            algorithm={name: torch.cat([stat(p, name) for p in parts]) for name in names},
            work=[
                replace(work, rows=work.rows + start)
                for part, start in zip(parts, starts, strict=True)
                for work in part.work
            ],
        )


class Engine:
    """The primitives for the agents ``variants`` of one run (see the module docstring)."""

    def __init__(
        self, run: RunConfig, variants: Mapping[int, EnvVariant], *, compiled: bool = False
    ) -> None:
        from fedhpg.common.worker import policy_and_spaces

        self.run = run
        self.variants = dict(variants)
        check_device(run.algo.device)
        self.device = torch.device(run.algo.device)
        first = self.variants[min(self.variants)]
        template, self.observation_space, self.action_space = policy_and_spaces(first, run)
        self.compiled: CompiledBackend | None = None
        """The compiled backend's sampling and gradients (``compiled``: the caller checked it
        serves these agents, :func:`fedhpg.common.batched.compiled_agents`)."""
        if compiled:
            from fedhpg.common.batched import mlp_shape
            from fedhpg.common.batched.backend import CompiledBackend

            self.compiled = CompiledBackend(mlp_shape(template))
        self.policy = PolicyRows(template, self.device)
        self.tiles_per_call = max(
            packed_elements(self.device) // (TILE * self.policy.num_params), 1
        )
        """Tiles one autograd call of the gradient pass takes (off the CPU, every call takes
        exactly so many, padded with empty tiles: a GPU library may pick its kernels, and so
        its order of additions, by a call's shape, which must then not depend on the
        company)."""
        self.act_tiles_per_call = act_tiles_per_call(
            self.device, self.policy.num_params, run.agents.num_agents
        )
        """Tiles of :data:`ACT_TILE` copies one policy call takes while sampling: off the CPU
        exactly so many (padded), for the same reason; None on the CPU (one call a step)."""
        self.step_bytes = StepBytes.of(
            self.observation_space,
            self.action_space,
            self.policy.num_params,
            self.policy.noise_size,
            self.device,
        )
        self._envs: dict[tuple[int, int], BatchEnv] = {}
        self._profiles: dict[int, AgentProfile] = {}
        self._gamma: dict[int, float] = {}
        self._horizon: dict[int, int] = {}
        self._family: DeviceFamily | None = None
        self._family_rows: dict[int, int] | None = None
        """Each agent's row of :attr:`_family` (None: not built yet)."""
        self._per_row: dict[str, torch.Tensor] = {}
        """The round's rows' constants on the device (:meth:`begin`)."""
        self._own_budgets: tuple[tuple[int, ...], list[Any]] | None = None
        """The last :meth:`round_budgets` of agents running their own budgets."""
        self._budget_rows: (
            tuple[list[Any], dict[str, torch.Tensor], dict[str, torch.Tensor]] | None
        ) = None
        """For the last list of budgets: its fields as rows and the rows' constants."""
        self.rows: Rows | None = None
        self.tally: Tally | None = None
        self._hook: Any = None
        self._clock = 0.0
        self._sampling_s = 0.0
        """Thread CPU seconds spent sampling since the last :meth:`finished`."""

    # -- per-agent constants ----------------------------------------------------------------

    def profile(self, k: int) -> AgentProfile:
        if k not in self._profiles:
            self._profiles[k] = agent_profile(self.run, k)
        return self._profiles[k]

    def gamma(self, k: int) -> float:
        if k not in self._gamma:
            self._gamma[k] = discount(self.run, self.variants[k])
        return self._gamma[k]

    def horizon(self, k: int) -> int:
        if k not in self._horizon:
            self._horizon[k] = training_horizon(self.run, self.variants[k])
        return self._horizon[k]

    def prepare(self) -> None:
        for k in self.variants:
            self.profile(k), self.gamma(k), self.horizon(k)
        self.family()

    def family(self) -> DeviceFamily | None:
        """The torch implementation's table of every agent's variant on the device, built once
        (None: the family has none, ``algo.envs=gymnasium``, or the compiled backend samples)."""
        if self._family_rows is None:
            order = sorted(self.variants)
            self._family_rows = {k: row for row, k in enumerate(order)}
            if self.compiled is None and self.run.algo.envs == "auto":
                self._family = device_family([self.variants[k] for k in order], self.device)
        return self._family

    def _batch_env(self, k: int, copies: int) -> BatchEnv:
        if (k, copies) not in self._envs:
            self._envs[(k, copies)] = self.variants[k].make_batch_env(copies)
        return self._envs[(k, copies)]

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    # -- a round ----------------------------------------------------------------------------

    def begin(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        hook: Any = None,
    ) -> Rows:
        """The rows of ``agents`` for a round from θ̃ (their budgets planned or their own)."""
        chosen = self.round_budgets(agents, budgets)
        if self._budget_rows is None or self._budget_rows[0] is not chosen:  # a new list
            names = list(vars(chosen[0])) if chosen else []
            as_rows = {
                name: torch.tensor([int(getattr(b, name)) for b in chosen], dtype=torch.int64)
                for name in names
            }
            self._budget_rows = (chosen, as_rows, self._row_constants(agents))
        _, budget_rows, self._per_row = self._budget_rows
        rows = Rows(
            agents=list(agents),
            theta=theta.detach().to(self.device, torch.float32).expand(len(agents), -1).clone(),
            budgets={name: values.clone() for name, values in budget_rows.items()},
            round_index=round_index,
        )
        self.rows, self.tally, self._hook = rows, Tally.zeros(rows.size), hook
        self._clock = time.thread_time()
        self._sampling_s = 0.0
        return rows

    def plan(
        self, agents: Sequence[int], copies: Sequence[int], horizons: Sequence[int]
    ) -> RoundPlan:
        """Chunks of ``agents`` (agent i holding ``copies[i]`` trajectories of up to
        ``horizons[i]`` steps at once) that fit ``algo.memory_gib`` on the device
        (``common/engine/memory.py``)."""
        budget = memory_budget(self.device, self.run.algo.memory_gib)
        return plan_round(copies, horizons, self.step_bytes, budget)

    def round_budgets(
        self, agents: Sequence[int], budgets: Mapping[int, Mapping[str, int]] | None = None
    ) -> list[Any]:
        """Each agent's budget for the round: its own, or with the server's plan put in. The
        list is kept, the same object, while the agents repeat and run their own budgets."""
        key = tuple(agents)
        own = not any((budgets or {}).get(k) for k in key)
        if own and self._own_budgets is not None and self._own_budgets[0] == key:
            return self._own_budgets[1]
        chosen = [planned_budget(self.profile(k).budget, (budgets or {}).get(k)) for k in key]
        self._own_budgets = (key, chosen) if own else None
        return chosen

    def _row_constants(self, agents: Sequence[int]) -> dict[str, torch.Tensor]:
        """What sampling and the estimator read of each row, as [A] tensors on the device (sent
        once a round, not at every iteration)."""
        self.family()
        assert self._family_rows is not None
        kinds = [attack_of(self.run.attack, k) for k in agents]

        def row(values: list[Any], dtype: torch.dtype) -> torch.Tensor:
            return torch.tensor(values, dtype=dtype).to(self.device)

        return {
            "agent": row(list(agents), torch.int64),
            "gamma": row([self.gamma(k) for k in agents], torch.float64),
            "horizon": row([self.horizon(k) for k in agents], torch.int64),
            "family_row": row([self._family_rows[k] for k in agents], torch.int64),
            "random_actions": row([a == "random_action" for a in kinds], torch.bool),
            "flipped_rewards": row([a == "reward_flip" for a in kinds], torch.bool),
        }

    def _rows(self) -> Rows:
        assert self.rows is not None, "begin() a round first"
        return self.rows

    def gammas(self) -> torch.Tensor:
        """γ_k of every row, [A] float64."""
        self._rows()
        return self._per_row["gamma"]

    def sample(
        self,
        theta: torch.Tensor,
        counts: torch.Tensor,
        *,
        iteration: int,
        purpose: Purpose = Purpose.TRAIN,
        greedy: bool = False,
        horizons: torch.Tensor | None = None,
    ) -> Trajectories:
        """``counts[a]`` trajectories of row a at θ row ``theta[a]`` (0: none)."""
        rows = self._rows()
        per_row = self._per_row
        wanted = counts.to(self.device)
        positions = torch.nonzero(wanted > 0).squeeze(1)
        limit = per_row["horizon"] if horizons is None else horizons.to(self.device)
        if len(positions) == len(wanted):  # every row samples: no row to leave out
            chosen, agents, agent_ids = wanted, rows.agents, per_row["agent"]
        else:
            chosen, limit = wanted[positions], limit[positions]
            agents = [rows.agents[i] for i in positions.tolist()]
            agent_ids = per_row["agent"][positions]
        keys = self._keys(agent_ids, chosen, rows.round_index, purpose, iteration)
        started = time.thread_time()
        try:
            batch = self._sample_rows(theta, positions, chosen, keys, limit, agents, greedy)
        finally:
            self._sampling_s += time.thread_time() - started
        return batch.regrouped(positions, rows.size)

    def _keys(
        self,
        agents: torch.Tensor,
        counts: torch.Tensor,
        round_index: int,
        purpose: Purpose,
        iteration: int,
    ) -> torch.Tensor:
        """The keys of trajectories 0 … ``counts[a]`` − 1 of each agent ``agents[a]``, row
        after row (:func:`~fedhpg.common.randomness.trajectory_keys`)."""
        if self.compiled is not None:
            return self.compiled.trajectory_keys(
                self.run.seed, agents, counts, round_index, purpose, iteration
            )
        owner = torch.repeat_interleave(torch.arange(len(counts), device=self.device), counts)
        starts = torch.cumsum(counts, 0) - counts
        index = torch.arange(int(counts.sum()), device=self.device) - starts[owner]
        return trajectory_keys(self.run.seed, agents, round_index, purpose, iteration, index, owner)

    def _sample_rows(
        self,
        theta: torch.Tensor,
        positions: torch.Tensor,
        chosen: torch.Tensor,
        keys: torch.Tensor,
        limit: torch.Tensor,
        agents: list[int],
        greedy: bool,
    ) -> Trajectories:
        """The rows ``positions`` (their agents ``agents``) sampled by the backend."""
        if self.compiled is not None:
            variants = [self.variants[k] for k in agents]
            rows = theta if len(positions) == theta.shape[0] else theta[positions]  # all, in order
            return self.compiled.sample(rows, chosen, keys, limit, agents, variants, greedy=greedy)
        per_row = self._per_row
        copies = make_copies(
            self.family(),
            per_row["family_row"][positions],
            chosen,
            self._batch_env,
            agents,
            self.device,
        )
        faults = None
        random_actions = per_row["random_actions"][positions]
        flipped_rewards = per_row["flipped_rewards"][positions]
        if not greedy and bool((random_actions | flipped_rewards).any()):
            faults = Faults(random_actions=random_actions, flipped_rewards=flipped_rewards)
        try:
            return sample(
                self.policy,
                copies,
                theta.to(self.device)[positions],
                chosen,
                keys,
                limit,
                greedy=greedy,
                faults=faults,
                action_space=self.action_space,
                tiles_per_call=self.act_tiles_per_call,
            )
        finally:
            copies.close()

    def coefficients(
        self, batch: Trajectories, weights: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The run's estimator coefficients of ``batch``, one per cell of ``batch.layout``
        [S] float64 (per-row baselines and discounts; ``weights`` [N] or [T, N] importance
        weights)."""
        algo = self.run.algo
        # weights past a trajectory's end, and a batch's standardisation in its cells' order,
        # need every cell the terms reach
        layout = (
            batch.grouped_layout
            if weights is not None or algo.normalize == "batch"
            else batch.layout
        )
        rewards, alive = batch.cells if layout is batch.layout else batch.cells_on(layout)
        if weights is not None and weights.dim() == 2:
            weights = layout.gather(weights)
        coefficients = estimators.coefficients(
            algo.estimator,  # type: ignore[arg-type]
            layout,
            rewards,
            alive,
            gamma=self.gammas()[batch.owner],
            baseline=algo.baseline,  # type: ignore[arg-type]
            weights=weights,
            reward_to_go=algo.reward_to_go,  # type: ignore[arg-type]
            normalize=algo.normalize,  # type: ignore[arg-type]
            groups=batch.owner,
        )
        if layout is batch.layout:
            return coefficients
        return coefficients.index_select(0, layout.cell(batch.layout.time, batch.layout.column))

    # -- the policy's maths per row ----------------------------------------------------------

    def _tiles(self, batch: Trajectories, group: torch.Tensor) -> _Tiles:
        """The alive steps of ``batch`` cut into tiles of :data:`TILE` steps, each tile the
        steps of one group (``group`` [N]: each column's; a group's columns contiguous)."""
        cells = torch.nonzero(batch.alive.T)  # (n, t): by column, columns grouped
        column, step = cells[:, 0], cells[:, 1]
        owner = group[column]
        groups = int(group.max()) + 1 if len(group) else 0
        per_group = torch.bincount(owner, minlength=groups)
        slot = (
            torch.arange(len(owner), device=owner.device)
            - (torch.cumsum(per_group, 0) - per_group)[owner]
        )
        tiles_per_group = (per_group + TILE - 1) // TILE
        tile_start = torch.cumsum(tiles_per_group, 0) - tiles_per_group
        tile = tile_start[owner] + slot // TILE
        total = int(tiles_per_group.sum())
        if self.device.type != "cpu" and total:  # whole calls only (``tiles_per_call``)
            total = -(-total // self.tiles_per_call) * self.tiles_per_call
        flat = step * batch.alive.shape[1] + column
        cell = batch.layout.cell(step, column)
        obs_flat = batch.obs.reshape(-1, *batch.obs.shape[2:])
        act_flat = batch.actions.reshape(-1, *batch.actions.shape[2:])
        obs = obs_flat.new_zeros((total, TILE, *batch.obs.shape[2:]))
        act = act_flat.new_zeros((total, TILE, *batch.actions.shape[2:]))
        put_distinct(obs, (tile, slot % TILE), obs_flat[flat])
        put_distinct(act, (tile, slot % TILE), act_flat[flat])
        tile_group = torch.repeat_interleave(
            torch.arange(groups, device=owner.device), tiles_per_group
        )
        if total > tile_group.shape[0]:  # empty tiles (no coefficient) of group 0
            tile_group = torch.cat([tile_group, tile_group.new_zeros(total - tile_group.shape[0])])
        return _Tiles(
            obs, act, tile, slot % TILE, flat, cell, tile_group, tile_start, tiles_per_group
        )

    def _tile_gradients(
        self, theta: torch.Tensor, row_of_tile: torch.Tensor, tiles: _Tiles, values: torch.Tensor
    ) -> torch.Tensor:
        """Each tile's Σ coef ∇ log π under its θ row ``theta[row_of_tile]``, [tiles, d], in
        chunks (the θ rows of one chunk's tiles at a time)."""
        coef = torch.zeros(tiles.obs.shape[:2], dtype=torch.float64, device=self.device)
        put_distinct(coef, (tiles.tile, tiles.slot), values[tiles.cell].to(torch.float64))
        out = theta.new_empty((tiles.obs.shape[0], self.policy.num_params))
        return self._over_tiles(tiles, out, lambda block: self.policy.score_gradients(
            theta[row_of_tile[block]], tiles.obs[block], tiles.act[block], coef[block]
        ))  # fmt: skip

    def _over_tiles(
        self, tiles: _Tiles, out: torch.Tensor, compute: Callable[[slice], torch.Tensor]
    ) -> torch.Tensor:
        """``out[block] = compute(block)`` over the tiles, as many at once as memory allows."""
        chunked(
            tiles.obs.shape[0],
            1,
            self.tiles_per_call,
            lambda block: out.__setitem__(block, compute(block)),
        )
        return out

    @staticmethod
    def _group_sums(tiles: _Tiles, per_tile: torch.Tensor, groups: int) -> torch.Tensor:
        """Each group's tile gradients summed in tile order (the same sums in any company);
        the empty tiles that pad a GPU's last call are left out."""
        real = int(tiles.tiles_per_group.sum())
        return ordered_sums(tiles.tile_group[:real], per_tile[:real], groups)

    def gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """Σ_n Σ_t coef[t, n] ∇ log π_θa(a_t|s_t) over each row a's trajectories n, [A, d]
        (zero for a row without trajectories; ``coefficients`` per cell of ``batch.layout``)."""
        if self.compiled is not None:
            return self.compiled.gradients(theta, batch, coefficients)
        tiles = self._tiles(batch, batch.owner)
        per_tile = self._tile_gradients(theta, tiles.tile_group, tiles, coefficients)
        return self._group_sums(tiles, per_tile, theta.shape[0])

    def mean_gradients(
        self, theta: torch.Tensor, batch: Trajectories, weights: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(1/B_a) Σ_n g(τ_n | θ_a) with the run's estimator, per row [A, d]."""
        gradient = self.gradients(theta, batch, self.coefficients(batch, weights))
        return gradient / batch.counts.clamp_min(1).to(gradient.dtype).unsqueeze(1)

    def log_probs(self, theta: torch.Tensor, batch: Trajectories) -> torch.Tensor:
        """log π_θa(a_t|s_t) of every alive step under its row's θ row, [T, N] (0 elsewhere)."""
        tiles = self._tiles(batch, batch.owner)
        values = tiles.obs.new_zeros(tiles.obs.shape[:2], dtype=torch.float64)
        self._over_tiles(tiles, values, lambda block: self.policy.log_probs(
            theta[tiles.tile_group[block]], tiles.obs[block], tiles.act[block]
        ).double())  # fmt: skip
        out = torch.zeros(batch.alive.numel(), dtype=torch.float64, device=self.device)
        put_distinct(out, tiles.flat, values[tiles.tile, tiles.slot])
        return out.reshape(batch.alive.shape)

    def trajectory_gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """g(τ_n | θ_{owner(n)}) of every trajectory, [N, d]."""
        columns = torch.arange(batch.alive.shape[1], device=self.device)
        tiles = self._tiles(batch, columns)
        per_tile = self._tile_gradients(theta, batch.owner[tiles.tile_group], tiles, coefficients)
        return self._group_sums(tiles, per_tile, len(columns))

    # -- bookkeeping -----------------------------------------------------------------------

    def finished(
        self,
        batch: Trajectories,
        *,
        clipped: torch.Tensor | None = None,
        grad_steps: torch.Tensor | None = None,
    ) -> None:
        """An iteration is done for the rows that sampled ``batch``: their totals, and the
        work each row did (its share of the iteration's CPU time, by env steps) to the hook."""
        tally = self.tally
        assert tally is not None
        now = time.thread_time()
        elapsed, self._clock = now - self._clock, now
        sampled, self._sampling_s = min(self._sampling_s, elapsed), 0.0
        counts = batch.counts.cpu()
        ran = torch.nonzero(counts > 0).squeeze(1)
        steps = batch.steps_per_row().cpu()
        returns = batch.per_row(batch.returns()).cpu()
        share = steps.double() / max(int(steps.sum()), 1)
        compute = share * elapsed
        tally.trajectories += counts
        tally.env_steps += steps
        tally.return_sum += returns
        tally.compute_s += compute
        tally.sample_s += share * sampled
        if clipped is not None:
            tally.clipped += clipped.cpu().long()
        grads = steps if grad_steps is None else grad_steps.cpu().clone()
        if len(ran) == len(counts):  # every row ran: whole tensors, no indexing
            numbers = tally.iterations.clone()
            tally.iterations += 1
            work = RowWork(ran, numbers, compute, steps, grads)
        else:
            numbers = tally.iterations[ran].clone()
            tally.iterations[ran] += 1
            work = RowWork(ran, numbers, compute[ran], steps[ran], grads[ran])
        tally.work.append(work)
        if self._hook is not None:
            self._hook(work)
        self._clock = time.thread_time()

    @contextmanager
    def untimed(self) -> Iterator[None]:
        """Work inside is left out of the rows' compute time (diagnostics)."""
        started = time.thread_time()
        try:
            yield
        finally:
            self._clock += time.thread_time() - started

    def report(self, name: str, values: torch.Tensor) -> None:
        """An algorithm statistic of every row, [A] (NaN: none for that row)."""
        assert self.tally is not None
        self.tally.algorithm[name] = values.detach().double().cpu()

    # -- evaluation --------------------------------------------------------------------------

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        """The return and success of θ̃ in each agent's environment (greedy per eval.greedy)."""
        rows = self.begin(round_index, theta, agents)
        horizons = torch.tensor([self.run.eval.horizon or self.horizon(k) for k in agents])
        counts = torch.full((rows.size,), episodes, dtype=torch.int64)
        batch = self.sample(
            rows.theta,
            counts,
            iteration=0,
            purpose=Purpose.EVALUATE,
            greedy=self.run.eval.greedy,
            horizons=horizons,
        )
        undiscounted = batch.returns().cpu()
        discounted = batch.returns(self.gammas()).cpu()
        lengths = batch.lengths().cpu().double()
        success = batch.success.cpu().double()
        owner = batch.owner.cpu()
        stats = {}
        for a, k in enumerate(rows.agents):
            mine = owner == a
            values = undiscounted[mine]
            stats[k] = EvaluationStats(
                return_mean=float(values.mean()),
                return_std=float(values.std(unbiased=False)),
                discounted_return_mean=float(discounted[mine].mean()),
                success_rate=float(success[mine].mean()),
                length_mean=float(lengths[mine].mean()),
                episodes=episodes,
            )
        self.rows = self.tally = None
        return stats
