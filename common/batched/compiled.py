"""The compiled backend: FedHPG for a group of CartPole agents with the MLP categorical
policy, each local iteration of all of them in two numba calls (sample, then learn).

It computes what the engine (:mod:`fedhpg.common.engine`) computes for FedHPG — the same
estimators, options, clipping and steps, every agent from its own random stream — an agent
at a time inside :mod:`fedhpg.common.batched.kernels` instead of all agents in lockstep
through torch. The floats differ from the engine's (another tanh, float64 dynamics, the
random numbers drawn otherwise), so ``algo.engine`` is dictated by the server; between
placements of one run they never differ, since every process that holds an agent runs the
same kernel on the same inputs for it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from fedhpg.common.batched import kernels
from fedhpg.common.batched.agents import EngineAgents, Lazy
from fedhpg.common.batched.mlp import MLPShape
from fedhpg.common.batched.streams import agent_streams
from fedhpg.common.bounds import SmoothnessProbe, bound_stats, gradient_moments
from fedhpg.common.components import planned_budget
from fedhpg.common.config import RunConfig
from fedhpg.common.group import Budgets, GroupHook
from fedhpg.common.round_columns import Interrupt, IterationColumns, TrainedColumns
from fedhpg.common.types import EvaluationStats, LocalResult
from fedhpg.common.worker import IterationWork, Stream
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.compiled import CARTPOLE_STEP_LIMIT, cartpole_table


def compiled_unsupported(run: RunConfig, variants: Mapping[int, EnvVariant]) -> str | None:
    """Why the compiled engine cannot train these agents (None: it can). The caller has
    checked what every batched engine needs (FedHPG, the MLP categorical policy)."""
    first = variants[min(variants)]
    if cartpole_table([first]) is None:
        return f"{type(first).__name__} {getattr(first, 'env_id', '')} (compiled: CartPole only)"
    return None


class CompiledFedHPG(EngineAgents):
    """The agents ``variants`` of a FedHPG run on CartPole variants (see the module docstring)."""

    def __init__(self, run: RunConfig, variants: Mapping[int, EnvVariant], shape: MLPShape):
        super().__init__(run, variants, shape)
        self.sizes = np.asarray(shape.sizes, dtype=np.int64)
        self.physics = Lazy(self._physics_of)
        self._buffers: _RowBuffers | None = None
        self._constants: tuple[tuple[int, ...], np.ndarray, np.ndarray, np.ndarray] | None = None
        algo = run.algo
        self.options = np.array(
            [
                kernels.ESTIMATORS[algo.estimator],
                kernels.BASELINES[algo.baseline],
                kernels.REWARD_TO_GO[algo.reward_to_go],
                kernels.NORMALIZE[algo.normalize],
                kernels.OPTIMIZERS[algo.optimizer],
            ],
            dtype=np.int64,
        )

    def prepare(self) -> None:
        super().prepare()
        self.physics.fill(self.variants)

    def _physics_of(self, k: int) -> np.ndarray:
        table = cartpole_table([self.variants[k]])
        if table is None:
            raise ValueError(f"agent {k}'s variant is not a CartPole the compiled engine models")
        return table[0]

    def _per_agent(self, order: Sequence[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The agents' horizons (a copy: evaluation writes it), discounts and physics rows,
        kept for the last set of agents (a host whose agents all train meets the same 500
        every round)."""
        key = tuple(order)
        if self._constants is None or self._constants[0] != key:
            horizons = np.array([self.horizons[k] for k in order], dtype=np.int64)
            gammas = np.array([self.gammas[k] for k in order], dtype=np.float64)
            physics = np.stack([self.physics[k] for k in order])
            self._constants = (key, horizons, gammas, physics)
        _, horizons, gammas, physics = self._constants
        return horizons.copy(), gammas, physics

    # -- training -------------------------------------------------------------------------

    def _rows(self, capacity: int) -> _RowBuffers:
        """The sampled rows' buffers, kept between rounds (a round of 500 agents with long
        episodes holds ~2 M rows: allocated afresh, their pages would be faulted in again)."""
        if self._buffers is None or self._buffers.capacity < capacity:
            self._buffers = _RowBuffers(capacity, self.shape.sizes[0])
        return self._buffers

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        on_iteration: GroupHook | None = None,
        budgets: Budgets | None = None,
    ) -> dict[int, LocalResult]:
        after = None
        if on_iteration is not None:
            hook = on_iteration

            def after(order: list[int], number: int, done: IterationColumns) -> None:
                for position, compute, steps in zip(
                    done.positions.tolist(),
                    done.compute_s.tolist(),
                    done.env_steps.tolist(),
                    strict=True,
                ):
                    hook(order[position], IterationWork(number, compute, steps, steps))

        trained = self._train(round_index, theta, agents, budgets, after)
        return {k: trained.result(i) for i, k in enumerate(trained.agents)}

    def train_columns(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        budgets: Budgets | None = None,
        interrupt: Interrupt | None = None,
    ) -> TrainedColumns:
        """The round as :meth:`train` computes it, as columns (an agent host's path)."""
        after = None
        if interrupt is not None:
            stop = interrupt

            def after(order: list[int], number: int, done: IterationColumns) -> None:
                stop()

        return self._train(round_index, theta, agents, budgets, after)

    def _train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        budgets: Budgets | None,
        after: Callable[[list[int], int, IterationColumns], None] | None,
    ) -> TrainedColumns:
        algo = self.run.algo
        order = sorted(agents)
        planned = budgets or {}
        chosen = [planned_budget(self.budget(k), planned.get(k)) for k in order]
        batch = np.array([b.batch_size for b in chosen], dtype=np.int64)
        iters = np.array([b.local_iters for b in chosen], dtype=np.int64)
        horizons, gammas, physics = self._per_agent(order)
        streams = agent_streams(self.run.seed, order, round_index, int(Stream.TRAIN))
        flat = theta.detach().numpy().astype(np.float32)
        thetas = np.repeat(flat[None, :], len(order), 0)
        firsts, seconds = np.zeros_like(thetas), np.zeros_like(thetas)
        most_rows = batch * np.minimum(horizons, CARTPOLE_STEP_LIMIT)  # per agent, at most
        rows = self._rows(int(min(most_rows.sum(), max(MAX_ROWS, most_rows.max()))))
        row_span = np.zeros((len(order), 2), dtype=np.int64)
        copy_start = np.zeros(len(order), dtype=np.int64)
        lengths = np.zeros(int(batch.sum()), dtype=np.int64)
        returns = np.zeros(int(batch.sum()), dtype=np.float64)
        clipped = np.zeros(len(order), dtype=np.bool_)
        done = np.zeros(len(order), dtype=np.int64)
        bounds = _BoundEstimates(order, batch, thetas.shape[1], algo.bound_estimates)
        totals = {name: np.zeros(len(order)) for name in ("steps", "returns", "compute", "clip")}
        iterations: list[IterationColumns] = []
        sample_s = gradient_s = 0.0
        clip = -1.0 if algo.grad_clip is None else float(algo.grad_clip)
        # An agent whose steps diverge samples from NaN logits until its round ends; the server
        # rejects its update and says why.
        for iteration in range(int(iters.max(initial=0))):
            for part in _parts(np.flatnonzero(iters > iteration), most_rows, rows.capacity):
                measure = bounds.wanted(iteration, part)
                before = thetas[measure].copy() if measure.any() else None
                started = time.thread_time()
                kernels.sample_iteration(thetas, self.sizes, physics, batch, horizons, gammas,
                                         streams, part, rows.obs, rows.action, rows.copy,
                                         rows.time, row_span, copy_start, lengths,
                                         returns)  # fmt: skip
                sampled = time.thread_time()
                kernels.learn_iteration(thetas, firsts, seconds, self.sizes, batch, gammas,
                                        done, part, rows.obs, rows.action, rows.copy,
                                        rows.time, rows.coef, row_span, copy_start, lengths,
                                        self.options, float(algo.step_size), clip, clipped,
                                        measure, bounds.per_trajectory, bounds.start,
                                        bounds.unclipped)  # fmt: skip
                learned = time.thread_time()
                if before is not None:
                    bounds.record(iteration, measure, before)
                sample_s += sampled - started
                gradient_s += learned - sampled
                copies = int(batch[part].sum())
                starts = copy_start[part]
                steps = np.add.reduceat(lengths[:copies], starts)
                cpu_per_step = (learned - started) / max(int(steps.sum()), 1)
                compute = cpu_per_step * steps
                totals["steps"][part] += steps
                totals["returns"][part] += np.add.reduceat(returns[:copies], starts)
                totals["compute"][part] += compute
                totals["clip"][part] += clipped[part]
                done[part] += 1
                # every CartPole step is differentiated once (grad_steps = env_steps)
                ran = IterationColumns(positions=part, compute_s=compute, env_steps=steps,
                                       grad_steps=steps)  # fmt: skip
                iterations.append(ran)
                if after is not None:
                    after(order, iteration, ran)
        trajectories = batch * iters
        share = totals["steps"] / max(float(totals["steps"].sum()), 1.0)
        algorithm: dict[str, list[float | None]] = {
            "engine_sample_s": (sample_s * share).tolist(),
            "engine_gradient_s": (gradient_s * share).tolist(),
        }
        for key, column in bounds.columns(len(order)).items():
            algorithm.setdefault(key, column)
        return TrainedColumns(
            agents=order,
            thetas=thetas,
            trajectories=trajectories,
            env_steps=totals["steps"].astype(np.int64),
            compute_s=totals["compute"],
            train_return=totals["returns"] / np.maximum(trajectories, 1),
            grad_clipped=totals["clip"].astype(np.int64),
            algorithm=algorithm,
            iterations=iterations,
        )

    # -- evaluation -----------------------------------------------------------------------

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        order = sorted(agents)
        horizons, gammas, physics = self._per_agent(order)
        if self.run.eval.horizon:
            horizons[:] = self.run.eval.horizon
        streams = agent_streams(self.run.seed, order, round_index, int(Stream.EVALUATE))
        flat = theta.detach().numpy().astype(np.float32)
        thetas = np.repeat(flat[None, :], len(order), 0)
        lengths = np.zeros(len(order) * episodes, dtype=np.int64)
        returns = np.zeros(len(order) * episodes, dtype=np.float64)
        discounted = np.zeros(len(order) * episodes, dtype=np.float64)
        kernels.evaluate_agents(thetas, self.sizes, physics, episodes, horizons, gammas, streams,
                                self.run.eval.greedy, lengths, returns, discounted)  # fmt: skip
        stats = {}
        for a, k in enumerate(order):
            block = slice(a * episodes, (a + 1) * episodes)
            stats[k] = EvaluationStats(
                return_mean=float(returns[block].mean()),
                return_std=float(returns[block].std()),
                discounted_return_mean=float(discounted[block].mean()),
                success_rate=0.0,  # CartPole has no goal
                length_mean=float(lengths[block].mean()),
                episodes=episodes,
            )
        return stats


MAX_ROWS = 1 << 21
"""Rows (one per sampled step) the buffers hold, ~56 MB: a local iteration whose agents could
sample more (500 agents of B = 64 at CartPole's 500 steps: 16 M) runs in parts of agents that
fit, one after another, which changes no agent's numbers."""


def _parts(agents: np.ndarray, most_rows: np.ndarray, capacity: int) -> list[np.ndarray]:
    """``agents`` (positions) cut, in order, into runs whose rows at most fit ``capacity``."""
    if int(most_rows[agents].sum()) <= capacity:
        return [agents]  # the usual case: all at once
    parts, start, filled = [], 0, 0
    for i, a in enumerate(agents.tolist()):
        if filled + most_rows[a] > capacity and i > start:
            parts.append(agents[start:i])
            start, filled = i, 0
        filled += int(most_rows[a])
    parts.append(agents[start:])
    return parts


class _RowBuffers:
    """Every sampled step of a local iteration: observation, action, copy, step and (once
    the batch is in) its estimator coefficient / B."""

    def __init__(self, capacity: int, obs_dim: int) -> None:
        self.capacity = capacity
        self.obs = np.empty((capacity, obs_dim), dtype=np.float32)
        self.action = np.empty(capacity, dtype=np.int32)
        self.copy = np.empty(capacity, dtype=np.int32)
        self.time = np.empty(capacity, dtype=np.int32)
        self.coef = np.empty(capacity, dtype=np.float32)


class _BoundEstimates:
    """``algo.bound_estimates`` in the compiled engine: each agent's first batch gives σ̂², M̂
    and ‖∇J‖² from its per-trajectory gradients, its first two give the secant L̂ (the numpy
    engine's figures, the same code from the per-trajectory gradients on; common/local.py)."""

    MEASURED_ITERATIONS = 2

    def __init__(self, order: Sequence[int], batch: np.ndarray, dim: int, on: bool) -> None:
        self.on = on
        self.batch = batch
        self.start = np.concatenate([[0], np.cumsum(batch)[:-1]]).astype(np.int64)
        rows = int(batch.sum()) if on else 0
        self.per_trajectory = np.zeros((rows, dim), dtype=np.float32)
        self.unclipped = np.zeros((len(order) if on else 0, dim), dtype=np.float32)
        self.found: dict[int, dict[str, float]] = {}
        self.probes: dict[int, SmoothnessProbe] = {}

    def wanted(self, iteration: int, active: np.ndarray) -> np.ndarray:
        measure = np.zeros(len(self.batch), dtype=np.bool_)
        if self.on and iteration < self.MEASURED_ITERATIONS:
            measure[active] = True
        return measure

    def record(self, iteration: int, measure: np.ndarray, before: np.ndarray) -> None:
        for row, i in enumerate(np.flatnonzero(measure).tolist()):
            first = int(self.start[i])
            trajectories = self.per_trajectory[first : first + int(self.batch[i])]
            if len(trajectories) < 2:
                continue
            stats = bound_stats(gradient_moments(torch.from_numpy(trajectories.copy())))
            if iteration == 0:
                self.found[i] = dict(stats)
            noise = stats["bound_variance"] / int(self.batch[i])
            probe = self.probes.setdefault(i, SmoothnessProbe())
            probe.add(torch.from_numpy(before[row]), torch.from_numpy(self.unclipped[i]), noise)
            self.found.setdefault(i, {}).update(probe.stats())

    def columns(self, agents: int) -> dict[str, list[float | None]]:
        """Each statistic found, as a column over the round's agents (None: not measured)."""
        names = dict.fromkeys(key for found in self.found.values() for key in found)
        return {
            key: [
                None if (value := self.found.get(i, {}).get(key)) is None else float(value)
                for i in range(agents)
            ]
            for key in names
        }


def warm_up() -> float:
    """Compile the kernels (or load them from numba's cache) on a toy batch of the types the
    engine passes; returns the seconds it took. The first compilation on a machine takes tens
    of seconds; ``make setup`` and the image build run this once so that runs load the cache,
    and ``fedhpg-run`` runs it before it forks agents, so that they inherit the compiled code
    instead of compiling it each."""
    started = time.perf_counter()
    sizes = np.array([4, 2, 2], dtype=np.int64)
    agents = 2
    thetas = np.zeros((agents, 16), dtype=np.float32)
    physics = np.tile(cartpole_table_defaults(), (agents, 1))
    batch = np.array([1, 2], dtype=np.int64)
    horizons = np.array([3, 3], dtype=np.int64)
    gammas = np.array([0.9, 0.9], dtype=np.float64)
    rows = np.flatnonzero(batch > 0)
    streams = agent_streams(0, [0, 1], 0, int(Stream.TRAIN))
    capacity = int((batch * horizons).sum())
    rows_obs = np.empty((capacity, 4), dtype=np.float32)
    action, copy, step = (np.empty(capacity, dtype=np.int32) for _ in range(3))
    row_span = np.zeros((agents, 2), dtype=np.int64)
    copy_start = np.zeros(agents, dtype=np.int64)
    lengths = np.zeros(int(batch.sum()), dtype=np.int64)
    returns = np.zeros(int(batch.sum()), dtype=np.float64)
    kernels.sample_iteration(thetas, sizes, physics, batch, horizons, gammas, streams, rows,
                             rows_obs, action, copy, step, row_span, copy_start, lengths,
                             returns)  # fmt: skip
    coef = np.empty(capacity, dtype=np.float32)
    measure = np.array([False, True])
    kernels.learn_iteration(thetas, np.zeros_like(thetas), np.zeros_like(thetas), sizes, batch,
                            gammas, np.zeros(agents, dtype=np.int64), rows, rows_obs, action, copy,
                            step, coef,
                            row_span, copy_start, lengths, np.zeros(5, dtype=np.int64), 1.0, -1.0,
                            np.zeros(agents, dtype=np.bool_), measure,
                            np.zeros((int(batch.sum()), 16), dtype=np.float32),
                            np.array([0, 1], dtype=np.int64),
                            np.zeros((agents, 16), dtype=np.float32))  # fmt: skip
    episodes = np.zeros(agents, dtype=np.int64), np.zeros(agents), np.zeros(agents)
    kernels.evaluate_agents(thetas, sizes, physics, 1, horizons, gammas, streams, True,
                            *episodes)  # fmt: skip
    return time.perf_counter() - started


def cartpole_table_defaults() -> np.ndarray:
    """One row of gymnasium CartPole-v1's own constants."""
    from fedhpg.envs.compiled import CARTPOLE_DEFAULTS

    return np.asarray(CARTPOLE_DEFAULTS, dtype=np.float64)


if __name__ == "__main__":  # make setup: fill numba's cache once
    print(f"compiled engine ready ({warm_up():.1f} s)")
