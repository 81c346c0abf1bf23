"""The torch backend: every policy, environment family and space, on ``algo.device``.

All rows sampled together (``common/learning/engine/sampling.py``: one episode in every copy of
every row, stepped in lockstep; the copies on the device for the families with a torch
implementation, through gymnasium otherwise), the estimator's torch definition
(``common/learning/engine/estimate.py``), and the policy's score-function maths per row in tiles of
:data:`TILE` steps, so that a row's floats never depend on the batch's shape or company.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.learning.attacks import attack_of
from fedhpg.common.learning.engine.backend import Draws, defined_mean_gradients
from fedhpg.common.learning.engine.copies import make_copies
from fedhpg.common.learning.engine.estimate import EstimatorOptions, batch_coefficients
from fedhpg.common.learning.engine.memory import packed_elements
from fedhpg.common.learning.engine.policy_rows import PolicyRows, chunked
from fedhpg.common.learning.engine.sampling import Faults, act_tiles_per_call, sample
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.randomness import trajectory_keys
from fedhpg.common.learning.staircase import ordered_sums
from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.device import DeviceFamily, device_family
from fedhpg.envs.tensor_writes import put_distinct

TILE = 64
"""Steps per tile of the policy's maths. Every per-row reduction over steps is made of
fixed-size tiles summed in order, so its floats never depend on the batch's shape (a matrix
product's blocking over a longer reduction would change the order of the additions)."""


RECENT_LISTS = 8
"""Lists of agents whose sampling settings are kept (a round's iterations repeat them)."""


@dataclass(frozen=True)
class _Places:
    """Where a batch's alive steps go in tiles of :data:`TILE` steps of one group each: each
    group's steps packed column after column (a column's in time order) from its first tile
    on, its last tile padded with zeros; the tiles past ``real`` (a GPU's last call's
    padding) hold nothing. Every move touches the alive steps alone, never the padded batch's
    dead cells (with short episodes of very different lengths, most of them)."""

    steps: _AliveSteps | None
    """Each alive step's cell and slot; None: the tiles are the batch's columns in order, cut
    in tiles (every step happened and every group fills whole tiles): a transpose, no index."""
    tiles: int
    real: int
    """Tiles that hold a group's steps."""

    def into(self, padded: torch.Tensor) -> torch.Tensor:
        """A padded [T, N, ...] tensor's alive cells in the tiles, [tiles, TILE, ...] (zero in
        the slots that hold no step)."""
        steps, columns, *rest = padded.shape
        if self.steps is None:
            # contiguous, as the indexed tiles are: a reduction's order follows the strides
            out = padded.transpose(0, 1).contiguous().view(self.real, TILE, *rest)
            if self.tiles > self.real:
                out = torch.cat([out, out.new_zeros((self.tiles - self.real, TILE, *rest))])
            return out
        flat = padded.reshape(steps * columns, *rest)
        return self.placed(flat.index_select(0, self.steps.cell))

    def placed(self, values: torch.Tensor) -> torch.Tensor:
        """Each alive step's ``values`` [R, ...] (in :class:`_AliveSteps`' order) in the
        tiles, [tiles, TILE, ...], zero in the slots that hold no step."""
        assert self.steps is not None
        out = values.new_zeros((self.tiles * TILE, *values.shape[1:]))
        if out.device.type == "cpu":
            out.index_copy_(0, self.steps.slot, values)
        else:  # each slot is named once: no deterministic sort needed
            put_distinct(out, self.steps.slot, values)
        return out.view(self.tiles, TILE, *values.shape[1:])

    def out_of(self, values: torch.Tensor, steps: int, columns: int) -> torch.Tensor:
        """Per-slot ``values`` [tiles, TILE] as the padded batch's [T, N] (zero where no step
        happened)."""
        if self.steps is None:
            return values[: self.real].reshape(columns, steps).T.contiguous()
        out = values.new_zeros(steps * columns)
        taken = values.reshape(-1).index_select(0, self.steps.slot)
        if out.device.type == "cpu":
            out.index_copy_(0, self.steps.cell, taken)
        else:  # each cell is named once
            put_distinct(out, self.steps.cell, taken)
        return out.view(steps, columns)


@dataclass(frozen=True)
class _AliveSteps:
    """A batch's alive steps, column after column (a column's in time order)."""

    time: torch.Tensor
    """[R] each step's t."""
    column: torch.Tensor
    """[R] each step's column of the batch."""
    cell: torch.Tensor
    """[R] its cell of the padded [T, N] batch, flat (t · N + n)."""
    slot: torch.Tensor
    """[R] its slot in the tiles' flat [tiles · TILE] slots."""


@dataclass(frozen=True)
class _Tiles:
    """A batch's alive steps cut into tiles of :data:`TILE` steps of one group each."""

    obs: torch.Tensor
    """[tiles, TILE, *obs_shape] (zeros past a group's last step)."""
    act: torch.Tensor
    places: _Places
    tile_group: torch.Tensor
    """Each tile's group."""
    tiles_per_group: torch.Tensor


@dataclass(frozen=True)
class _RowSettings:
    """What sampling reads of each row of a list of agents, [A] on the device."""

    family_row: torch.Tensor
    random_actions: torch.Tensor
    flipped_rewards: torch.Tensor


class TorchBackend:
    """:class:`~fedhpg.common.learning.engine.backend.Backend` in torch for the agents ``variants``
    (see the module docstring)."""

    def __init__(
        self,
        run: RunConfig,
        variants: dict[int, EnvVariant],
        policy: PolicyRows,
        spaces: tuple[gym.Space[Any], gym.Space[Any]],
        device: torch.device,
    ) -> None:
        self.run = run
        self.variants = variants
        self.policy = policy
        self.observation_space, self.action_space = spaces
        self.device = device
        self.tiles_per_call = max(packed_elements(device) // (TILE * policy.num_params), 1)
        """Tiles one autograd call of the gradient pass takes (off the CPU, every call takes
        exactly so many, padded with empty tiles: a GPU library may pick its kernels, and so
        its order of additions, by a call's shape, which must then not depend on the
        company)."""
        self.act_tiles_per_call = act_tiles_per_call(
            device, policy.num_params, run.agents.num_agents
        )
        """Tiles of :data:`~fedhpg.common.learning.engine.sampling.ACT_TILE` copies one policy call
        takes while sampling: off the CPU exactly so many (padded), for the same reason; None
        on the CPU (one call a step)."""
        self._envs: dict[tuple[int, int], BatchEnv] = {}
        self._family: DeviceFamily | None = None
        self._family_rows: dict[int, int] | None = None
        """Each agent's row of :attr:`_family` (None: not built yet)."""
        self._settings: dict[tuple[int, ...], _RowSettings] = {}
        """The settings of recent lists of agents (a round's iterations repeat them)."""

    def family(self) -> DeviceFamily | None:
        """Every agent's variant as a table on the device, built once (None: the family has
        no torch implementation, or ``algo.envs=gymnasium``)."""
        if self._family_rows is None:
            order = sorted(self.variants)
            self._family_rows = {k: row for row, k in enumerate(order)}
            if self.run.algo.envs == "auto":
                self._family = device_family([self.variants[k] for k in order], self.device)
        return self._family

    def _batch_env(self, k: int, copies: int) -> BatchEnv:
        if (k, copies) not in self._envs:
            self._envs[(k, copies)] = self.variants[k].make_batch_env(copies)
        return self._envs[(k, copies)]

    def _row_settings(self, agents: Sequence[int]) -> _RowSettings:
        key = tuple(agents)
        if key not in self._settings:
            if len(self._settings) >= RECENT_LISTS:
                self._settings.clear()
            self.family()
            assert self._family_rows is not None
            kinds = [attack_of(self.run.attack, k) for k in agents]

            def row(values: list[object], dtype: torch.dtype) -> torch.Tensor:
                return torch.tensor(values, dtype=dtype).to(self.device)

            self._settings[key] = _RowSettings(
                family_row=row([self._family_rows[k] for k in agents], torch.int64),
                random_actions=row([a.acts_randomly for a in kinds], torch.bool),
                flipped_rewards=row([a.flips_rewards for a in kinds], torch.bool),
            )
        return self._settings[key]

    def prepare(self) -> None:
        self.family()

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    # -- sampling ----------------------------------------------------------------------------

    def keys(self, draws: Draws, counts: torch.Tensor) -> torch.Tensor:
        counts = counts.to(self.device)
        owner = torch.repeat_interleave(torch.arange(len(counts), device=self.device), counts)
        starts = torch.cumsum(counts, 0) - counts
        index = torch.arange(int(counts.sum()), device=self.device) - starts[owner]
        return trajectory_keys(draws.seed, draws.agents, draws.round_index, draws.purpose,
                               draws.iteration, index, owner)  # fmt: skip

    def sample(
        self,
        theta: torch.Tensor,
        counts: torch.Tensor,
        draws: Draws,
        horizons: torch.Tensor,
        agents: Sequence[int],
        *,
        greedy: bool,
    ) -> Trajectories:
        keys = self.keys(draws, counts)
        settings = self._row_settings(agents)
        counts = counts.to(self.device)
        copies = make_copies(
            self.family(), settings.family_row, counts, self._batch_env, agents, self.device
        )
        faults = None
        if not greedy and bool((settings.random_actions | settings.flipped_rewards).any()):
            faults = Faults(
                random_actions=settings.random_actions, flipped_rewards=settings.flipped_rewards
            )
        try:
            return sample(
                self.policy,
                copies,
                theta.to(self.device),
                counts,
                keys,
                horizons.to(self.device),
                greedy=greedy,
                faults=faults,
                action_space=self.action_space,
                tiles_per_call=self.act_tiles_per_call,
            )
        finally:
            copies.close()

    def mean_gradients(
        self,
        theta: torch.Tensor,
        batch: Trajectories,
        options: EstimatorOptions,
        gammas: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        return defined_mean_gradients(self, theta, batch, options, gammas, weights)

    def coefficients(
        self,
        batch: Trajectories,
        options: EstimatorOptions,
        gammas: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        """One per cell of ``batch.layout``, [S] float64."""
        return batch_coefficients(batch, options, gammas, weights)

    # -- the policy's maths per row ----------------------------------------------------------

    def _tiles(self, batch: Trajectories, group: torch.Tensor) -> _Tiles:
        """The alive steps of ``batch`` cut into tiles of :data:`TILE` steps, each tile the
        steps of one group (``group`` [N]: each column's; a group's columns contiguous, the
        groups in order)."""
        alive = batch.alive
        steps, columns = alive.shape
        groups = int(group.max()) + 1 if columns else 0
        columns_per_group = torch.bincount(group, minlength=groups)
        group_end = torch.cumsum(columns_per_group, 0)
        lengths = batch.lengths()
        taken = torch.cat([group_end.new_zeros(1), torch.cumsum(lengths, 0)])
        per_group = taken[group_end] - taken[group_end - columns_per_group]
        tiles_per_group = (per_group + TILE - 1) // TILE
        tile_start = torch.cumsum(tiles_per_group, 0) - tiles_per_group
        real, alive_steps = torch.stack([tiles_per_group.sum(), taken[-1]]).tolist()
        total = real
        if self.device.type != "cpu" and total:  # whole calls only (``tiles_per_call``)
            total = -(-total // self.tiles_per_call) * self.tiles_per_call
        alive_at = None
        if alive_steps != steps * columns or real * TILE != alive_steps:
            # a column's alive steps are its first lengths[n]: step r of the packed order is
            # column n's step r − taken[n], and its group's tiles start TILE · tile_start
            column = torch.repeat_interleave(
                torch.arange(columns, device=alive.device), lengths, output_size=alive_steps
            )
            rank = torch.arange(alive_steps, device=alive.device)
            time = rank - taken.index_select(0, column)
            shift = TILE * tile_start - (torch.cumsum(per_group, 0) - per_group)
            alive_at = _AliveSteps(
                time=time,
                column=column,
                cell=time * columns + column,
                slot=rank + shift.index_select(0, group).index_select(0, column),
            )
        places = _Places(alive_at, total, real)
        tile_group = torch.repeat_interleave(
            torch.arange(groups, device=alive.device), tiles_per_group
        )
        if total > real:  # empty tiles (no coefficient) of group 0
            tile_group = torch.cat([tile_group, tile_group.new_zeros(total - real)])
        return _Tiles(
            places.into(batch.obs), places.into(batch.actions), places, tile_group,
            tiles_per_group,
        )  # fmt: skip

    def _tile_gradients(
        self,
        theta: torch.Tensor,
        row_of_tile: torch.Tensor,
        tiles: _Tiles,
        values: torch.Tensor,
        batch: Trajectories,
    ) -> torch.Tensor:
        """Each tile's Σ coef ∇ log π under its θ row ``theta[row_of_tile]``, [tiles, d], in
        chunks (the θ rows of one chunk's tiles at a time); ``values`` per cell of
        ``batch.layout``."""
        values = values.to(torch.float64)
        alive_at = tiles.places.steps
        if alive_at is None:
            coef = tiles.places.into(_padded(batch, values))
        else:  # each alive step's cell of the layout, straight into its slot
            coef = tiles.places.placed(
                values.index_select(0, batch.layout.cell(alive_at.time, alive_at.column))
            )
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
        real = tiles.places.real
        return ordered_sums(tiles.tile_group[:real], per_tile[:real], groups)

    def gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """Σ_n Σ_t coef[t, n] ∇ log π_θa(a_t|s_t) over each row a's trajectories n, [A, d]
        (zero for a row without trajectories; ``coefficients`` per cell of ``batch.layout``)."""
        tiles = self._tiles(batch, batch.owner)
        per_tile = self._tile_gradients(theta, tiles.tile_group, tiles, coefficients, batch)
        return self._group_sums(tiles, per_tile, theta.shape[0])

    def log_probs(self, theta: torch.Tensor, batch: Trajectories) -> torch.Tensor:
        """log π_θa(a_t|s_t) of every alive step under its row's θ row, [T, N] float64 (0
        elsewhere)."""
        tiles = self._tiles(batch, batch.owner)
        values = tiles.obs.new_empty(tiles.obs.shape[:2], dtype=torch.float64)
        self._over_tiles(tiles, values, lambda block: self.policy.log_probs(
            theta[tiles.tile_group[block]], tiles.obs[block], tiles.act[block]
        ).double())  # fmt: skip
        return tiles.places.out_of(values, *batch.alive.shape)

    def trajectory_gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """g(τ_n | θ_{owner(n)}) of every trajectory, [N, d]."""
        columns = torch.arange(batch.alive.shape[1], device=self.device)
        tiles = self._tiles(batch, columns)
        per_tile = self._tile_gradients(
            theta, batch.owner[tiles.tile_group], tiles, coefficients, batch
        )
        return self._group_sums(tiles, per_tile, len(columns))


def _padded(batch: Trajectories, values: torch.Tensor) -> torch.Tensor:
    """Per-cell ``values`` of ``batch.layout`` as the padded batch's [T, N] (zero past each
    column's cells)."""
    layout = batch.layout
    steps, columns = batch.alive.shape
    if layout.size == steps * columns:  # every column T cells: the cells in [T, N] order
        return values.view(steps, columns)
    out = values.new_zeros(steps * columns)
    cells = layout.time * columns + layout.column
    if out.device.type == "cpu":
        out.index_copy_(0, cells, values)
    else:
        put_distinct(out, cells, values)
    return out.view(steps, columns)
