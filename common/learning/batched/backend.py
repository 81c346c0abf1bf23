"""The compiled backend: the engine's primitives for CartPole agents with the MLP
categorical policy, in numba on the CPU (:class:`~fedhpg.common.learning.engine.backend.Backend`).

Sampling, the keys and the score gradients run an agent at a time inside
:mod:`fedhpg.common.learning.batched.kernels`, several times faster than torch's lockstep on a CPU
(BENCHMARKS.md); log-probabilities are the torch backend's, on the same batch. Each copy
draws from its own trajectory key with the engine's own hash (common/learning/randomness.py), so an
agent's trajectories depend on it alone; the floats differ from the torch backend's (float64
dynamics, a float32 rational tanh), so ``algo.engine`` is dictated by the server, and between
placements of one run they never differ.
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch

from fedhpg.common.learning import randomness
from fedhpg.common.learning.batched import fused, kernels
from fedhpg.common.learning.batched.estimator import (
    KernelOptions,
    kernel_options,
    packed_coefficients,
)
from fedhpg.common.learning.batched.kernels import ACTION, COLUMN, TIME
from fedhpg.common.learning.batched.mlp import MLPShape
from fedhpg.common.learning.engine.backend import Draws, defined_mean_gradients
from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.engine.host_arrays import HostArrays
from fedhpg.common.learning.engine.torch_backend import TorchBackend
from fedhpg.common.learning.engine.trajectories import StepRows, Trajectories
from fedhpg.common.learning.randomness import Purpose
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.compiled import CARTPOLE_DEFAULTS, CARTPOLE_STEP_LIMIT, cartpole_table

_ONE = np.ones(1, dtype=np.float64)
"""CartPole's reward, every step's."""


def _ones(size: int) -> np.ndarray:
    """``size`` rewards of 1 as a view of one (stride 0: no memory a step; read, never
    written)."""
    return np.ndarray((size,), np.float64, _ONE, 0, (0,))


RECENT_ROWS = 8
"""Sets of rows :meth:`CompiledBackend._physics_rows` keeps (a round's local iterations)."""


@functools.cache
def _run_key(seed: int, purpose: int) -> int:
    """The (seed, purpose) part of every trajectory key, hashed once."""
    return randomness.key_of(seed, purpose)


def covers(variant: EnvVariant) -> bool:
    """Whether the compiled CartPole models this variant."""
    return cartpole_table([variant]) is not None


class CompiledBackend:
    """The primitives of an MLP categorical policy on CartPole variants (``variants``: the
    group's agents; ``torch``: the torch backend of the same agents, for log-probabilities)."""

    def __init__(
        self,
        shape: MLPShape,
        variants: dict[int, EnvVariant] | None = None,
        torch_backend: TorchBackend | None = None,
    ) -> None:
        self.shape = shape
        self.variants = variants or {}
        self._torch = torch_backend
        self.sizes = np.asarray(shape.sizes, dtype=np.int64)
        self._obs_size = int(shape.sizes[0])
        self._row_of: dict[int, int] = {}
        self._tables: list[np.ndarray] = []
        self._table: np.ndarray | None = None
        self._recent: dict[tuple[int, ...], np.ndarray] = {}
        """The physics rows of recent calls' agents (a round's iterations repeat them)."""
        self._buffers = _RowBuffers()
        self._chunk = _ChunkArrays()
        self._host = HostArrays()
        """Host views of the tensors the engine passes again and again (budgets, constants,
        a round's θ rows)."""
        self._unweighted: tuple[EstimatorOptions, KernelOptions] | None = None
        """The run's estimator options and their kernels' form without importance weights."""
        self._constants = _Constants()

    def _physics_rows(self, agents: Sequence[int]) -> np.ndarray:
        """The rows' physics tables, [A, P] (each agent's built once, kept in one array; the
        rows of recent calls kept for the next round's same iterations)."""
        key = tuple(agents)
        if key in self._recent:
            return self._recent[key]
        for k in agents:
            if k not in self._row_of:
                table = cartpole_table([self.variants[k]])
                if table is None:
                    raise ValueError(f"agent {k}'s variant is not a CartPole the backend models")
                self._row_of[k] = len(self._row_of)
                self._tables.append(table[0])
                self._table = None
        if self._table is None:
            self._table = np.stack(self._tables)
            self._recent.clear()
        if len(self._recent) >= RECENT_ROWS:
            self._recent.clear()
        self._recent[key] = self._table[[self._row_of[k] for k in agents]]
        return self._recent[key]

    def keys(self, draws: Draws, counts: torch.Tensor) -> torch.Tensor:
        """:func:`~fedhpg.common.learning.randomness.trajectory_keys` of trajectories 0 …
        ``counts[a]`` − 1 of every row a, row after row: the same words, in one compiled
        call."""
        wanted = self._host(counts)
        out = np.empty(int(wanted.sum()), dtype=np.int64)
        base, agents, round_word, iteration_word = self._key_words(draws)
        kernels.trajectory_keys(base, agents, wanted, round_word, iteration_word, out)
        return torch.from_numpy(out)

    def coefficients(
        self,
        batch: Trajectories,
        options: EstimatorOptions,
        gammas: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        """One per packed step of the batch, [R] float64, in the order of its steps (the torch
        definition's bits: :mod:`fedhpg.common.learning.batched.estimator`)."""
        steps = self._packed_steps(batch)
        return torch.from_numpy(
            packed_coefficients(
                options,
                steps.rewards.numpy(),
                steps.time.numpy(),
                steps.column.numpy(),
                batch.lengths().numpy(),
                batch.owner.numpy(),
                gammas.numpy(),
                None if weights is None else weights.detach().double().numpy(),
            )
        )

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
        """One episode per copy of every row, as the engine's ``sample`` returns them. Drawn
        when first needed (:class:`_Draw`): by :meth:`mean_gradients` with the gradients, a
        few agents at a time, or whole (:func:`~fedhpg.common.learning.batched.fused.
        keyed_sample`) when a primitive reads the steps; the same numbers either way."""
        count = self._host(counts)  # int64 rows, as the engine makes them
        limits = np.minimum(self._host(horizons), CARTPOLE_STEP_LIMIT)
        draw = _Draw(
            self._key_words(draws),
            np.array(self._host(theta), dtype=np.float32, order="C"),  # θ as it is now
            self._physics_rows(agents),
            count,
            limits,
            greedy,
        )
        trajectories = len(draw.lengths)
        # the tensors as a loop first reads them: a lone agent's FedHPG reads none of them
        return Trajectories(
            success=lambda: self._constants.false(trajectories),  # CartPole has no goal
            owner=lambda: torch.from_numpy(self._summary(draw).owner),
            counts=counts,
            lengths=lambda: torch.from_numpy(self._summary(draw).lengths),
            steps=lambda: self._packed(self._whole(draw)),
            # 1 a step, exactly
            returns=lambda: torch.from_numpy(self._summary(draw).lengths.astype(np.float64)),
            row_sums=lambda: self._summary(draw).row_sums(),
            sampling_s=lambda: draw.seconds,
            native=draw,
        )

    def _summary(self, draw: _Draw) -> _Draw:
        """``draw`` with its lengths, rows and row starts written (drawn whole if nothing
        drew it yet)."""
        if not draw.summarised:
            self._whole(draw)
        return draw

    def _whole(self, draw: _Draw) -> _Sampled:
        """Every step of ``draw``, drawn in one compiled call the first time."""
        if draw.whole is None:
            started = time.thread_time()
            capacity = int(draw.count @ draw.limits)
            obs, actions, columns, times = self._buffers.take(capacity, self._obs_size)
            written = fused.keyed_sample(
                *draw.words, draw.thetas, self.sizes, draw.physics, draw.count, draw.limits,
                draw.greedy, obs, actions, columns, times, draw.lengths, draw.owner,
                draw.row_start,
            )  # fmt: skip
            draw.whole = _Sampled(
                obs, actions, columns, times, written, draw.lengths, draw.owner, draw.row_start
            )
            draw.summarised = True
            draw.seconds += time.thread_time() - started
        return draw.whole

    def _thetas(self, theta: torch.Tensor) -> np.ndarray:
        """θ rows as the kernels read them: float32, C-ordered (a view where they are)."""
        return np.ascontiguousarray(self._host(theta), dtype=np.float32)

    def _key_words(self, draws: Draws) -> tuple[int, np.ndarray, int, int]:
        """``draws`` as the key kernels take them: the run's key, the agents, the round and
        the iteration as signed 64-bit words."""
        return (
            _run_key(draws.seed, int(draws.purpose)),
            self._host(draws.agents),
            randomness.signed(draws.round_index),
            randomness.signed(draws.iteration),
        )

    def _packed(self, sampled: _Sampled) -> StepRows:
        """The batch's steps as the torch maths takes them (int64 actions and indices)."""
        written = sampled.written

        def wide(values: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(values[:written].astype(np.int64))

        return StepRows(
            obs=torch.from_numpy(sampled.obs[:written]),
            actions=wide(sampled.actions),
            rewards=self._constants.ones(written),  # CartPole: 1 a step, the last too
            time=wide(sampled.times),
            column=wide(sampled.columns),
            rows=self._constants.arange(len(sampled.row_start) - 1),
            row_start=torch.from_numpy(sampled.row_start),
        )

    def mean_gradients(
        self,
        theta: torch.Tensor,
        batch: Trajectories,
        options: EstimatorOptions,
        gammas: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        """:meth:`gradients` with :meth:`coefficients`, each row's divided by its
        trajectories, in one compiled call for a batch this backend sampled and an
        unstandardised estimator: a batch not drawn yet drawn with them a chunk of rows at a
        time (:func:`~fedhpg.common.learning.batched.fused.sampled_gradients`, without
        importance weights), else on its steps (:func:`~fedhpg.common.learning.batched.fused.
        estimated_gradients`); the same kernels and the same float32 division, so the same
        bits. Composed otherwise."""
        draw = batch.native
        if weights is None:
            if self._unweighted is None or self._unweighted[0] is not options:
                self._unweighted = (options, kernel_options(options))
            chosen = self._unweighted[1]  # made once: every iteration asks for the same
        else:
            chosen = kernel_options(options, weights.detach().double().numpy())
        if not isinstance(draw, _Draw) or not chosen.plain:
            return defined_mean_gradients(self, theta, batch, options, gammas, weights)
        positions = None
        if batch.num_rows != len(draw.count):  # renamed rows: some sampled none
            positions = torch.nonzero(batch.counts).squeeze(1)
            theta, gammas = theta[positions], gammas[positions]
        out = np.zeros((theta.shape[0], theta.shape[1]), dtype=np.float32)
        if not draw.summarised and weights is None:  # drawn here, a chunk at a time
            capacity = fused.chunk_capacity(draw.count, draw.limits, fused.CHUNK_STEPS)
            _, seconds = fused.sampled_gradients(
                *draw.words, draw.thetas, self._thetas(theta), self.sizes, draw.physics,
                draw.count, draw.limits, draw.greedy, chosen.gpomdp, chosen.mean_baseline,
                chosen.from_step, chosen.weights, self._host(gammas), fused.CHUNK_STEPS,
                *self._chunk.take(capacity, self._obs_size), draw.lengths,
                draw.owner, draw.row_start, out,
            )  # fmt: skip
            draw.summarised = True
            draw.seconds += seconds
        else:
            sampled = self._whole(draw)
            fused.estimated_gradients(
                chosen.gpomdp, chosen.mean_baseline, chosen.from_step, chosen.weighting,
                chosen.weights, self._host(gammas), sampled.times, sampled.columns,
                sampled.lengths, sampled.owner, _ones(sampled.written), self._thetas(theta),
                self.sizes, sampled.obs, sampled.actions, sampled.row_start, out,
            )  # fmt: skip
        means = torch.from_numpy(out)
        if positions is None:
            return means
        return means.new_zeros((batch.num_rows, out.shape[1])).index_copy_(0, positions, means)

    def gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """Σ_n Σ_t coef[t, n] ∇ log π_θa(a_t|s_t) over each row a's trajectories, [A, d], from
        the batch's packed steps (``coefficients``: one per step, :meth:`coefficients`)."""
        steps = self._packed_steps(batch)
        every_row = len(steps.rows) == theta.shape[0]  # then the rows are 0 … A − 1 in order
        part = self._gradients(
            theta if every_row else theta[steps.rows],
            steps,
            coefficients,
            self._constants.arange(len(coefficients)),
            steps.row_start,
        )
        if every_row:
            return part
        out = torch.zeros((theta.shape[0], theta.shape[1]), dtype=torch.float32)
        out[steps.rows] = part
        return out

    def trajectory_gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """g(τ_n | θ_{owner(n)}) of every trajectory, [N, d]: the steps regrouped by trajectory
        (each one's in time order), a trajectory a row of the gradient kernel."""
        steps = self._packed_steps(batch)
        order = torch.from_numpy(np.lexsort((steps.time.numpy(), steps.column.numpy())))
        columns = int(batch.owner.shape[0])
        per_column = torch.bincount(steps.column, minlength=columns)
        starts = torch.cat([per_column.new_zeros(1), torch.cumsum(per_column, 0)])
        by_column = replace(steps, obs=steps.obs[order], actions=steps.actions[order])
        return self._gradients(theta[batch.owner], by_column, coefficients, order, starts)

    def _gradients(
        self,
        thetas: torch.Tensor,
        steps: StepRows,
        coefficients: torch.Tensor,
        at: torch.Tensor,
        row_start: torch.Tensor,
    ) -> torch.Tensor:
        """Row i of ``thetas`` against steps ``row_start[i]`` … ``row_start[i + 1]`` − 1 of
        ``steps``' observations and actions, step r's coefficient ``coefficients[at[r]]``."""
        out = np.zeros((thetas.shape[0], thetas.shape[1]), dtype=np.float32)
        kernels.row_gradients(
            np.ascontiguousarray(thetas.detach().numpy(), dtype=np.float32),
            self.sizes,
            steps.obs.numpy(),
            steps.actions.numpy(),
            coefficients.numpy(),
            at.numpy(),
            row_start.numpy(),
            out,
        )
        return torch.from_numpy(out)

    @staticmethod
    def _packed_steps(batch: Trajectories) -> StepRows:
        """The batch's alive steps packed row after row (as the sampler wrote them: this
        backend's batches are always packed)."""
        if batch.steps is None:
            raise ValueError("the compiled backend takes the batches its own sampler packed")
        return batch.steps

    def prepare(self) -> None:
        self._physics_rows(sorted(self.variants))

    def log_probs(self, theta: torch.Tensor, batch: Trajectories) -> torch.Tensor:
        """The torch backend's, on this batch (the policy's float32 maths in torch)."""
        if self._torch is None:
            raise ValueError("this compiled backend was made without a torch backend")
        return self._torch.log_probs(theta, batch)

    def close(self) -> None:
        if self._torch is not None:
            self._torch.close()


class _Draw:
    """A sample asked for and not yet drawn whole: what draws it (its keys' words, the θ rows
    as they were when it was asked for, the rows' physics, trajectories and step limits) and
    what drawing it writes (each trajectory's length and row, each row's first step).
    :meth:`CompiledBackend.mean_gradients` draws it a few agents at a time with their
    gradients, never holding every step at once; a primitive that reads the steps draws it
    whole. The keys fix every draw, so both give the same numbers."""

    def __init__(
        self,
        words: tuple[int, np.ndarray, int, int],
        thetas: np.ndarray,
        physics: np.ndarray,
        count: np.ndarray,
        limits: np.ndarray,
        greedy: bool,
    ) -> None:
        self.words, self.thetas, self.physics = words, thetas, physics
        self.count, self.limits, self.greedy = count, limits, greedy
        trajectories = int(count.sum())
        self.lengths = np.zeros(trajectories, dtype=np.int64)
        self.owner = np.empty(trajectories, dtype=np.int64)
        self.row_start = np.empty(len(count) + 1, dtype=np.int64)
        self.summarised = False
        """Whether :attr:`lengths`, :attr:`owner` and :attr:`row_start` are written."""
        self.whole: _Sampled | None = None
        """Every step, once drawn whole."""
        self.seconds = 0.0
        """Thread CPU seconds spent drawing it so far."""

    def row_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """Each row's steps and undiscounted return (CartPole: 1 a step)."""
        per_row = self.row_start[1:] - self.row_start[:-1]
        return per_row, per_row.astype(np.float64)


class _Sampled(NamedTuple):
    """A batch as the sampler wrote it: the output arrays of its packed steps (reused by a
    later call only once no batch holds them: :class:`_RowBuffers`), the steps written, each
    trajectory's length and row, each row's first step."""

    obs: np.ndarray
    actions: np.ndarray
    columns: np.ndarray
    times: np.ndarray
    written: int
    lengths: np.ndarray
    owner: np.ndarray
    row_start: np.ndarray


class _Constants:
    """Read-only tensors a batch shares with the next (ones, falses, 0 … n − 1), grown as
    needed and handed out as prefixes: a batch never writes into its own."""

    def __init__(self) -> None:
        self._ones = torch.ones(0, dtype=torch.float64)
        self._false = torch.zeros(0, dtype=torch.bool)
        self._arange = torch.arange(0)

    @staticmethod
    def _grown(kept: torch.Tensor, size: int, make: Callable[[int], torch.Tensor]) -> torch.Tensor:
        return kept if kept.shape[0] >= size else make(max(size, 2 * kept.shape[0]))

    def ones(self, size: int) -> torch.Tensor:
        self._ones = self._grown(self._ones, size, lambda n: torch.ones(n, dtype=torch.float64))
        return self._ones[:size]

    def false(self, size: int) -> torch.Tensor:
        self._false = self._grown(self._false, size, lambda n: torch.zeros(n, dtype=torch.bool))
        return self._false[:size]

    def arange(self, size: int) -> torch.Tensor:
        self._arange = self._grown(self._arange, size, torch.arange)
        return self._arange[:size]


class _RowBuffers:
    """The sampler's output arrays, kept for the next call once no batch holds them.

    A call's arrays are sized for every copy running to its horizon (millions of rows for a
    host's agents), and the kernel writes its rows into them: allocated afresh at every call,
    their pages would be faulted in (and zeroed by the kernel) again each time. A batch's
    tensors are views of these arrays, so a set is reused only when nothing refers to it any
    more (its reference count); while the previous iteration's batch is alive the next call
    takes a second set."""

    def __init__(self) -> None:
        self.sets: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def take(
        self, capacity: int, obs_dim: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        for i, arrays in enumerate(self.sets):
            if _holders(arrays) == _UNREFERENCED:
                if arrays[0].shape[0] >= capacity and arrays[0].shape[1] == obs_dim:
                    return arrays
                del self.sets[i]  # free, but too small: replaced by a larger set
                break
        arrays = (
            np.empty((capacity, obs_dim), dtype=np.float32),
            np.empty(capacity, dtype=ACTION),
            np.empty(capacity, dtype=COLUMN),
            np.empty(capacity, dtype=TIME),
        )
        self.sets.append(arrays)
        return arrays


_Arrays5 = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class _ChunkArrays:
    """The arrays :func:`~fedhpg.common.learning.batched.fused.sampled_gradients` draws a
    chunk's steps into (no batch holds them), kept from call to call and grown when a call
    needs more: rewards (a view of one 1), observations, actions, trajectories, times."""

    def __init__(self) -> None:
        self.arrays: _Arrays5 | None = None

    def take(self, capacity: int, obs_dim: int) -> _Arrays5:
        if self.arrays is None or self.arrays[1].shape[0] < capacity:
            size = max(capacity, 2 * self.arrays[1].shape[0] if self.arrays else 0)
            self.arrays = (
                _ones(size),
                np.empty((size, obs_dim), dtype=np.float32),
                np.empty(size, dtype=ACTION),
                np.empty(size, dtype=COLUMN),
                np.empty(size, dtype=TIME),
            )
        return self.arrays


def _holders(arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> tuple[int, ...]:
    """The references to each array of a set (a batch holds them, and each view of one)."""
    obs, actions, columns, times = arrays
    count = sys.getrefcount
    return count(obs), count(actions), count(columns), count(times)


_UNREFERENCED = _holders((np.empty(0), np.empty(0), np.empty(0), np.empty(0)))
"""What :func:`_holders` counts for a set that only its tuple holds."""


def warm_up() -> float:
    """Compile the kernels (or load them from numba's cache) on a toy batch of the types the
    engine passes; returns the seconds it took. The first compilation on a machine takes tens
    of seconds; ``make setup`` and the image build run this once so that runs load the cache,
    and ``fedhpg-run`` runs it before it forks agents, so that they inherit the compiled code
    instead of compiling it each."""
    started = time.perf_counter()
    backend = CompiledBackend(MLPShape((4, 2, 2)))
    backend._row_of, backend._tables = {0: 0}, [np.asarray(CARTPOLE_DEFAULTS, dtype=np.float64)]
    theta = torch.zeros((2, 16))
    draws = Draws(0, torch.tensor([0, 1]), 0, Purpose.TRAIN, 0)
    counts, horizons = torch.tensor([1, 2]), torch.tensor([3, 3])
    gammas = torch.full((2,), 0.99, dtype=torch.float64)
    fresh = backend.sample(theta, counts, draws, horizons, [0, 0], greedy=False)
    backend.mean_gradients(theta, fresh, EstimatorOptions(), gammas, None)  # drawn with them
    batch = backend.sample(theta, counts, draws, horizons, [0, 0], greedy=True)
    # drawn whole: the estimator, plain and standardised (its second kernel), and both
    # gradient kernels
    for options in (EstimatorOptions(), EstimatorOptions(normalize="batch")):
        coefficients = backend.coefficients(batch, options, gammas, None)
    backend.gradients(theta, batch, coefficients)
    backend.trajectory_gradients(theta, batch, coefficients)
    backend.mean_gradients(theta, batch, EstimatorOptions(), gammas, None)
    return time.perf_counter() - started
