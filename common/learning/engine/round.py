"""A round of some agents' local updates: their rows, the primitives an algorithm's loop is
written with, and what the round did.

:meth:`Engine.begin <fedhpg.common.learning.engine.engine.Engine.begin>` returns a :class:`Round`;
an algorithm (``common/learning/algorithms/<name>.py``) runs its one loop over the round's θ rows
[A, d] with:

- :meth:`Round.sample`: B trajectories per row, drawn at each row's own θ from its own
  environment variant (keys: seed, agent, round, purpose, iteration, trajectory);
- :meth:`Round.coefficients`: the run's estimator (``common/learning/engine/estimate.py``) for them;
- :meth:`Round.gradients`, :meth:`Round.log_probs`, :meth:`Round.trajectory_gradients`: the
  policy's score-function maths per row;
- :meth:`Round.mean_gradients`: a batch's mean gradient with the run's estimator (its
  coefficients, then its gradients, in one backend call);
- :meth:`Round.finished`: the bookkeeping of an iteration (its statistics; cancellation), and
  :meth:`Round.report` for the algorithm's own statistics.

On the host an iteration's statistics go into the round's totals as it finishes. On a device
they stay there until the round's :attr:`Round.tally` is first read after its loop, then come
to the host once: every iteration's per-row counts in one copy and their returns in another
(nothing waits on a device inside the loop).

The primitives are the backend's (:class:`~fedhpg.common.learning.engine.backend.Backend`), chosen
once per group; the round adds whose draws they are and the tally. Rows are placement-free: what
a row computes depends on its agent, round and θ alone.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace

import numpy as np
import torch

from fedhpg.common.learning.engine.backend import Backend, Draws
from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.engine.host_arrays import HostArrays
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.randomness import Purpose
from fedhpg.common.records.round_columns import IterationColumns


@dataclass
class Tally:
    """Per-row totals of a round (``UpdateStats``) as host arrays, and its work per
    iteration."""

    trajectories: np.ndarray
    env_steps: np.ndarray
    return_sum: np.ndarray
    compute_s: np.ndarray
    clipped: np.ndarray
    sample_s: np.ndarray
    """Each row's share of the CPU time spent sampling (the rest of ``compute_s`` went to
    its gradients and steps)."""
    algorithm: dict[str, np.ndarray] = field(default_factory=dict)
    """Per-row algorithm statistics (float64); NaN where a row has none."""
    work: list[IterationColumns] = field(default_factory=list)

    @classmethod
    def zeros(cls, rows: int) -> Tally:
        """Zero totals, whose arrays are rows of two blocks (:meth:`blocks`)."""
        trajectories, env_steps, clipped = np.zeros((3, rows), dtype=np.int64)
        return_sum, compute_s, sample_s = np.zeros((3, rows), dtype=np.float64)
        return cls(trajectories, env_steps, return_sum, compute_s, clipped, sample_s)

    def blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """The integer totals (trajectories, env steps, clipped) and the float ones (return
        sum, compute, sampling) as [3, A] arrays whose rows are the fields: one addition
        updates three fields. Only for a :meth:`zeros` tally."""
        ints, floats = self.trajectories.base, self.return_sum.base
        assert isinstance(ints, np.ndarray) and isinstance(floats, np.ndarray)
        return ints, floats

    @classmethod
    def concatenated(cls, parts: Sequence[Tally]) -> Tally:
        """The tallies of consecutive chunks of a round's rows as one (its works' rows
        renumbered in the whole round)."""
        if len(parts) == 1:
            return parts[0]
        names = list(dict.fromkeys(name for part in parts for name in part.algorithm))

        def stat(part: Tally, name: str) -> np.ndarray:
            values = part.algorithm.get(name)
            return values if values is not None else np.full_like(part.sample_s, math.nan)

        starts = [0]
        for part in parts[:-1]:
            starts.append(starts[-1] + int(part.trajectories.shape[0]))
        return cls(
            **{
                name: np.concatenate([getattr(p, name) for p in parts])
                for name in (f.name for f in fields(cls))
                if name not in ("algorithm", "work")
            },
            algorithm={name: np.concatenate([stat(p, name) for p in parts]) for name in names},
            work=[
                replace(work, positions=work.positions + start)
                for part, start in zip(parts, starts, strict=True)
                for work in part.work
            ],
        )


Numbers = torch.Tensor | np.ndarray
"""A row's numbers of an iteration: a tensor, or a host array where the backend has them so."""

Interrupt = Callable[[], None]
"""Called after each iteration; it may raise to cancel the round."""


def _copied_to_host(values: Sequence[Numbers]) -> np.ndarray:
    """Device tensors [A] each stacked as one host array [len(values), A], in one copy."""
    return torch.stack([torch.as_tensor(v) for v in values]).numpy(force=True)


@dataclass(frozen=True)
class RowConstants:
    """What sampling and the estimator read of each row, [A] tensors on the device (made once
    for a list of agents, not at every iteration)."""

    agent: torch.Tensor
    gamma: torch.Tensor
    """float64."""
    horizon: torch.Tensor


@dataclass(frozen=True)
class BudgetRows:
    """The budgets of a round's rows (made once for a list of budgets, shared by the rounds
    that repeat it; read-only)."""

    rows: dict[str, torch.Tensor]
    """Each budget field as [A] int64 on the host (the configured budget, or the round's
    plan)."""
    spans: dict[str, tuple[int, int]]
    """Each field's (least, most) over the rows: how many iterations every row runs and how
    many some row does, known without reading a tensor."""


class Round:
    """The rows of one round's agents and the primitives their algorithm's loop uses (see the
    module docstring)."""

    def __init__(
        self,
        *,
        backend: Backend,
        options: EstimatorOptions,
        seed: int,
        round_index: int,
        agents: Sequence[int],
        theta: torch.Tensor,
        budgets: BudgetRows,
        constants: RowConstants,
        interrupt: Interrupt | None = None,
        host: HostArrays | None = None,
    ) -> None:
        self.backend = backend
        self._host = HostArrays() if host is None else host
        """Host views of the counts the loop passes (its budgets: the same tensors every
        iteration)."""
        self.options = options
        self.seed = seed
        """The run's seed (an algorithm's own draws, e.g. FedPG-BR's B_t, are keyed by it)."""
        self.round_index = round_index
        self.agents = list(agents)
        self.theta = theta
        """[A, d]: every row starts from θ̃."""
        self._budgets = budgets
        self.constants = constants
        self._tally = Tally.zeros(len(self.agents))
        self._totals = self._tally.blocks()
        self._interrupt = interrupt
        self._on_device = theta.device.type != "cpu"
        """Whether the rows' numbers are on a device (else on the host, added as they come)."""
        self._pending: list[tuple[Numbers, Numbers, Numbers, torch.Tensor | None, Numbers]] = []
        """On a device, each finished iteration's numbers per row, [A] each: its trajectories,
        env steps and differentiated steps (int64), whether its gradient was clipped (bool;
        None: none was) and its sum of undiscounted returns (float64)."""
        self._times: list[tuple[float, float]] = []
        """On a device, each finished iteration's CPU seconds, and those of them spent
        sampling."""
        self._reported: dict[str, torch.Tensor] = {}
        self._every_row: np.ndarray | None = None
        self._clock = time.thread_time()
        self._sampling_s = 0.0
        """Thread CPU seconds spent sampling since the last :meth:`finished`."""

    @property
    def size(self) -> int:
        return len(self.agents)

    def budget(self, name: str) -> torch.Tensor:
        """Budget field ``name`` of every row, [A] int64 on the host (read-only)."""
        return self._budgets.rows[name]

    def budget_span(self, name: str) -> tuple[int, int]:
        """The least and the most of :meth:`budget` ``name`` over the rows."""
        return self._budgets.spans[name]

    @property
    def gammas(self) -> torch.Tensor:
        """γ_k of every row, [A] float64."""
        return self.constants.gamma

    # -- the primitives ----------------------------------------------------------------------

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
        constants = self.constants
        limit = constants.horizon if horizons is None else horizons
        positions = None
        agents, agent_ids = self.agents, constants.agent
        if self._fewest(counts) == 0:  # some rows sample nothing: the others only, renamed after
            positions = torch.nonzero(counts > 0).squeeze(1)
            theta, counts, limit = theta[positions], counts[positions], limit[positions]
            agents = [self.agents[i] for i in positions.tolist()]
            agent_ids = agent_ids[positions]
        draws = Draws(self.seed, agent_ids, self.round_index, purpose, iteration)
        started = time.thread_time()
        try:
            batch = self.backend.sample(theta, counts, draws, limit, agents, greedy=greedy)
        finally:
            self._sampling_s += time.thread_time() - started
        return batch if positions is None else batch.regrouped(positions, self.size)

    def _fewest(self, counts: torch.Tensor) -> int:
        """The least of ``counts``: its span where it is a budget row (as a loop passes its
        budget), else read from its host view where it is on the host."""
        budgets = self._budgets
        for name, row in budgets.rows.items():
            if counts is row:
                return budgets.spans[name][0]
        if counts.device.type == "cpu":
            return int(self._host(counts).min())
        return int(counts.min())

    def coefficients(
        self, batch: Trajectories, weights: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The run's estimator coefficients of ``batch`` (per-row baselines and discounts;
        ``weights`` [N] or [T, N] importance weights), in the backend's own layout: what
        :meth:`gradients` and :meth:`trajectory_gradients` take."""
        return self.backend.coefficients(batch, self.options, self.gammas, weights)

    def gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """Σ_n Σ_t coef[t, n] ∇ log π_θa(a_t|s_t) over each row a's trajectories n, [A, d]
        (zero for a row without trajectories)."""
        return self.backend.gradients(theta, batch, coefficients)

    def mean_gradients(
        self, theta: torch.Tensor, batch: Trajectories, weights: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(1/B_a) Σ_n g(τ_n | θ_a) with the run's estimator, per row [A, d] (0 for a row
        without trajectories)."""
        return self.backend.mean_gradients(theta, batch, self.options, self.gammas, weights)

    def log_probs(self, theta: torch.Tensor, batch: Trajectories) -> torch.Tensor:
        """log π_θa(a_t|s_t) of every alive step under its row's θ row, [T, N] float64 (0
        elsewhere)."""
        return self.backend.log_probs(theta, batch)

    def trajectory_gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """g(τ_n | θ_{owner(n)}) of every trajectory, [N, d]."""
        return self.backend.trajectory_gradients(theta, batch, coefficients)

    # -- bookkeeping -------------------------------------------------------------------------

    def finished(
        self,
        batch: Trajectories,
        *,
        clipped: torch.Tensor | None = None,
        grad_steps: torch.Tensor | None = None,
    ) -> None:
        """An iteration is done for the rows that sampled ``batch``: its per-row numbers and
        its CPU time go into the totals (on a device they wait there, and the :attr:`tally`
        takes them to the host in one copy); then the round may be cancelled."""
        now = time.thread_time()
        elapsed, self._clock = now - self._clock, now
        sampled = min(self._sampling_s + batch.late_sampling_s(), elapsed)
        self._sampling_s = 0.0
        steps, returns = batch.row_totals()
        differentiated = steps if grad_steps is None else grad_steps
        if self._on_device:  # brought to the host with the tally, in one copy
            self._pending.append((batch.counts, steps, differentiated, clipped, returns))
            self._times.append((elapsed, sampled))
        else:
            self._add(
                self._array(batch.counts),
                self._array(steps),
                self._array(differentiated),
                None if clipped is None else clipped.numpy(force=True),
                self._array(returns),
                elapsed,
                sampled,
            )
        if self._interrupt is not None:
            self._interrupt()
            self._clock = time.thread_time()

    @property
    def tally(self) -> Tally:
        """What the round did so far: the finished iterations' totals and each one's work per
        row (its share of the iteration's CPU time, by env steps); on a device, the numbers
        waiting there brought to the host first (the counts in one copy, the returns in
        another) and added in the order they ran."""
        if self._pending:
            pending, self._pending = self._pending, []
            times, self._times = self._times, []
            counts = _copied_to_host([number for numbers in pending for number in numbers[:3]])
            returns = _copied_to_host([numbers[4] for numbers in pending])
            clips: list[Numbers] = [numbers[3] for numbers in pending if numbers[3] is not None]
            clipped = iter(_copied_to_host(clips) if clips else [])
            for i, (numbers, (elapsed, sampled)) in enumerate(zip(pending, times, strict=True)):
                trajectories, steps, differentiated = counts[3 * i : 3 * i + 3]
                self._add(
                    trajectories,
                    steps,
                    differentiated,
                    None if numbers[3] is None else next(clipped),
                    returns[i],
                    elapsed,
                    sampled,
                )
        if self._reported:
            for name, values in self._reported.items():
                self._tally.algorithm[name] = values.cpu().numpy()
            self._reported = {}
        return self._tally

    def _add(
        self,
        counts: np.ndarray,
        steps: np.ndarray,
        grad_steps: np.ndarray,
        clipped: np.ndarray | None,
        returns: np.ndarray,
        elapsed: float,
        sampled: float,
    ) -> None:
        """An iteration's per-row trajectories, env steps and differentiated steps (int64
        [A]), whether each row's gradient was clipped ([A] bool; None: none was) and its
        return sums (float64 [A]), with its (elapsed, sampling) CPU seconds shared by env
        steps, into the totals; iterations come in the order they ran (the float totals'
        order of additions)."""
        ints, floats = self._totals
        ints[0] += counts
        ints[1] += steps
        if clipped is not None:
            ints[2] += clipped
        shares = steps / max(int(steps.sum()), 1)
        compute = shares * elapsed
        floats[0] += returns
        floats[1] += compute
        floats[2] += shares * sampled
        if counts.all():  # every row ran: whole rows, no indexing
            work = IterationColumns(self._positions(), compute, steps, grad_steps)
        else:
            at = np.flatnonzero(counts)
            work = IterationColumns(at, compute[at], steps[at], grad_steps[at])
        self._tally.work.append(work)

    def _array(self, numbers: Numbers) -> np.ndarray:
        """Host ``numbers`` as an array (a tensor's view; the same one while it is the same
        tensor, as the budget rows are)."""
        return numbers if isinstance(numbers, np.ndarray) else self._host(numbers)

    def _positions(self) -> np.ndarray:
        """0 … A − 1, made once a round."""
        if self._every_row is None:
            self._every_row = np.arange(len(self.agents))
        return self._every_row

    @contextmanager
    def untimed(self) -> Iterator[None]:
        """Work inside is left out of the rows' compute time (diagnostics)."""
        started = time.thread_time()
        try:
            yield
        finally:
            self._clock += time.thread_time() - started

    def report(self, name: str, values: torch.Tensor) -> None:
        """An algorithm statistic of every row, [A] (NaN: none for that row); it reaches the
        host with the :attr:`tally`."""
        self._reported[name] = values.detach().double()
