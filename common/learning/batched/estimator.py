"""The policy-gradient estimator's coefficients compiled (numba), for the compiled backend.

:func:`fedhpg.common.learning.estimators.coefficients`, applied to a batch by
:func:`fedhpg.common.learning.engine.estimate.batch_coefficients`, is the definition: REINFORCE and
GPOMDP, the leave-one-out mean baselines, both rewards-to-go, both standardisations,
importance weights. On the CPU it costs a few dozen torch calls per batch (and a few per step
of its longest trajectory), which a lone agent's round pays at every local iteration and
which outweighs the sampling of a short batch. :func:`packed_coefficients` is the same
computation on the compiled sampler's packed steps in one compiled call (two with a
standardisation, torch's square roots between them), a few microseconds;
``tests/test_compiled_estimator.py`` holds it bit-equal to the torch definition
(``np.array_equal`` on float64, for every option, any company of rows and any order of the
packed steps).

How the bits are kept. Each row (an agent's trajectories) is laid out as the torch oracle's
grouped staircase (:meth:`~fedhpg.common.learning.staircase.Staircase.of_groups`) lays it out: every
trajectory extended to the row's longest with reward 0 (and its own importance weights) past
its end, the cells time-major and, at each step, the row's trajectories in column order. Every
number is then formed by the torch code's own operations in its order, without fused
multiply-adds (strict IEEE: no ``fastmath``, so LLVM may neither reassociate nor contract):

- γ^t by running products along time (1, then the previous power times γ), never ``pow``;
- sums over a row's trajectories (``ordered_sums``, CPU ``index_add_``) from 0.0, in column
  order; the standardisations' sums over the row's (or trajectory's) cells in cell order;
- GPOMDP's per-step baseline at every step up to the row's longest trajectory, dead steps
  included: x = v·(1 + 1/o) − S_t/o, o = max(count − 1, 1), S_t the row's sum at step t;
- tail sums R_t = x_t + R_{t+1} (from_step: x_t + γ·R_{t+1}) from the row's longest step down,
  so a trajectory's last step adds the tail of the cells past its end as torch's does;
- REINFORCE's totals by the same tail recurrence; its baseline (T − t_n)/(count − 1) with T
  the row's sum of totals;
- standardising: mean, centred² (x·x, as torch's ``x**2``), their sqrt, + ``NORMALIZE_EPS``,
  ``mask · centred / (sd + ε)``. The square roots are torch's own: on the CPU torch takes them
  from MKL (vdSqrt), whose root of ~1 % of float64 inputs is one ulp from the correctly rounded
  one that LLVM's ``sqrt`` gives, and MKL's code path may depend on the host's CPU.

A row's numbers use its own cells only, so they never depend on the rows beside it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from fedhpg.common.configuration.vocabularies import BASELINES, ESTIMATORS
from fedhpg.common.learning.batched.kernels import kernel
from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.estimators import NORMALIZE_EPS

_REWARD_TO_GO = {"from_start": 0, "from_step": 1}
_NORMALIZE = {"none": 0, "batch": 1, "episode": 2}
_NO_WEIGHTS = np.zeros((0, 0), dtype=np.float64)

_NONE, _BATCH, _EPISODE = 0, 1, 2
NO_STANDARDISATION = _NONE
""":func:`coefficient_cells`' ``normalize`` for coefficients left unstandardised."""
_UNWEIGHTED, _PER_TRAJECTORY, _PER_DECISION = 0, 1, 2


@kernel()
def _reinforce_row(
    grid: np.ndarray,
    alive: np.ndarray,
    gamma: float,
    mean_baseline: bool,
    weighting: int,
    weights: np.ndarray,
    first: int,
) -> None:
    """One row's REINFORCE coefficients on its cells ``grid`` [L, c] (rewards in, mask ·
    coefficient out): Σ_h γ^h r_h by the tail recurrence, less the other trajectories' mean,
    times the trajectory's weight."""
    steps, count = grid.shape
    discount = 1.0
    for t in range(steps):  # γ^t r_t; γ^t a running product
        if t > 0:
            discount = discount * gamma
        for j in range(count):
            grid[t, j] = discount * grid[t, j]
    for t in range(steps - 2, -1, -1):  # R_t = v_t + R_{t+1}: the totals in row 0
        for j in range(count):
            grid[t, j] = grid[t, j] + grid[t + 1, j]
    if mean_baseline:
        total = 0.0
        for j in range(count):
            total += grid[0, j]
        others = max(count - 1.0, 1.0)
        for j in range(count):
            loo = (total - grid[0, j]) / others if count > 1 else 0.0
            grid[0, j] = grid[0, j] - loo
    if weighting == _PER_TRAJECTORY:
        for j in range(count):
            grid[0, j] = grid[0, j] * weights[0, first + j]
    for t in range(steps - 1, -1, -1):  # row 0 last: it holds the centred totals
        for j in range(count):
            grid[t, j] = (1.0 if alive[t, j] else 0.0) * grid[0, j]


@kernel()
def _gpomdp_row(
    grid: np.ndarray,
    alive: np.ndarray,
    gamma: float,
    mean_baseline: bool,
    from_step: bool,
    weighting: int,
    weights: np.ndarray,
    first: int,
) -> None:
    """One row's GPOMDP coefficients on its cells ``grid`` [L, c] (rewards in, coefficient ·
    mask out): the per-step baseline at every step, weights, tail sums."""
    steps, count = grid.shape
    if not from_step:
        discount = 1.0
        for t in range(steps):
            if t > 0:
                discount = discount * gamma
            for j in range(count):
                grid[t, j] = discount * grid[t, j]
    if mean_baseline:
        others = float(max(count - 1, 1))
        keep = 1.0 + 1.0 / others
        for t in range(steps):
            total = 0.0
            for j in range(count):
                total += grid[t, j]
            share = total / others
            for j in range(count):
                grid[t, j] = grid[t, j] * keep - share
    if weighting == _PER_TRAJECTORY:
        for t in range(steps):
            for j in range(count):
                grid[t, j] = grid[t, j] * weights[0, first + j]
    elif weighting == _PER_DECISION:
        for t in range(steps):
            for j in range(count):
                grid[t, j] = grid[t, j] * weights[t, first + j]
    for t in range(steps - 2, -1, -1):
        for j in range(count):
            later = gamma * grid[t + 1, j] if from_step else grid[t + 1, j]
            grid[t, j] = grid[t, j] + later
    for t in range(steps):
        for j in range(count):
            grid[t, j] = grid[t, j] * (1.0 if alive[t, j] else 0.0)


@kernel()
def _moments(
    grid: np.ndarray, alive: np.ndarray, low: int, high: int, means: np.ndarray,
    spreads: np.ndarray, group: int,
) -> None:  # fmt: skip
    """The mean and the mean centred square of the alive cells of the row's trajectories
    ``low`` … ``high`` − 1, over every cell in cell order (time-major, columns in order), a
    dead cell adding its 0 · (c − mean) as torch's masked sums do."""
    steps = grid.shape[0]
    cells = 0.0
    for t in range(steps):
        for j in range(low, high):
            cells += 1.0 if alive[t, j] else 0.0
    cells = max(cells, 1.0)
    total = 0.0
    for t in range(steps):
        for j in range(low, high):
            total += grid[t, j] * (1.0 if alive[t, j] else 0.0)
    mean = total / cells
    spread = 0.0
    for t in range(steps):
        for j in range(low, high):
            centred = grid[t, j] - mean
            spread += centred * centred * (1.0 if alive[t, j] else 0.0)
    means[group], spreads[group] = mean, spread / cells


@kernel()
def coefficient_cells(
    gpomdp: bool,
    mean_baseline: bool,
    from_step: bool,
    normalize: int,
    weighting: int,
    rewards: np.ndarray,
    time: np.ndarray,
    column: np.ndarray,
    lengths: np.ndarray,
    owner: np.ndarray,
    gammas: np.ndarray,
    weights: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(the coefficients before any standardisation on every row's cells [S], each packed
    step's cell [R], the standardisation's means and mean squares, one per row or per
    trajectory): step i's unstandardised coefficient is ``grid[cell[i]]``, which a gradient
    kernel reads in place."""
    packed, columns, rows = rewards.shape[0], lengths.shape[0], gammas.shape[0]
    if time.shape[0] != packed or column.shape[0] != packed or owner.shape[0] != columns:
        raise ValueError("rewards, time and column need one entry a step, owner one a column")
    if weighting != _UNWEIGHTED and weights.shape[1] != columns:
        raise ValueError("importance weights need one column per trajectory")
    first = np.zeros(rows, dtype=np.int64)  # each row's columns: first … first + count − 1
    count = np.zeros(rows, dtype=np.int64)
    longest = np.zeros(rows, dtype=np.int64)
    steps = 0
    for n in range(columns):
        row = owner[n]
        if row < 0 or row >= rows or (n > 0 and row < owner[n - 1]):
            raise ValueError("owner must be nondecreasing rows of gammas")
        if lengths[n] < 1:
            raise ValueError("every trajectory has at least one step")
        if count[row] == 0:
            first[row] = n
        count[row] += 1
        longest[row] = max(longest[row], lengths[n])
        steps += lengths[n]
    if steps != packed:
        raise ValueError("the packed steps must be every step of every trajectory")
    base = np.zeros(rows + 1, dtype=np.int64)  # each row's cells: its grouped staircase
    for row in range(rows):
        base[row + 1] = base[row] + longest[row] * count[row]
        if weighting == _PER_DECISION and longest[row] > weights.shape[0]:
            raise ValueError("per-decision weights need a row per step of the longest")
    grid = np.zeros(base[rows], dtype=np.float64)  # a reward of 0 past each trajectory's end
    alive = np.zeros(base[rows], dtype=np.bool_)
    cell = np.empty(packed, dtype=np.int64)
    for i in range(packed):
        n, t = column[i], time[i]
        if n < 0 or n >= columns or t < 0 or t >= lengths[n]:
            raise ValueError("a packed step outside its trajectory")
        row = owner[n]
        at = base[row] + t * count[row] + (n - first[row])
        if alive[at]:
            raise ValueError("a step packed twice")
        alive[at] = True
        grid[at] = rewards[i]
        cell[i] = at
    groups = rows if normalize == _BATCH else columns if normalize == _EPISODE else 0
    means, spreads = np.zeros(groups, dtype=np.float64), np.zeros(groups, dtype=np.float64)
    for row in range(rows):
        if count[row] == 0:
            continue
        shape = (longest[row], count[row])
        cells = grid[base[row] : base[row + 1]].reshape(shape)
        mask = alive[base[row] : base[row + 1]].reshape(shape)
        gamma = gammas[row]
        if gpomdp:
            _gpomdp_row(cells, mask, gamma, mean_baseline, from_step, weighting, weights,
                        first[row])  # fmt: skip
        else:
            _reinforce_row(cells, mask, gamma, mean_baseline, weighting, weights, first[row])
        if normalize == _BATCH:
            _moments(cells, mask, 0, count[row], means, spreads, row)
        elif normalize == _EPISODE:
            for j in range(count[row]):
                _moments(cells, mask, j, j + 1, means, spreads, first[row] + j)
    return grid, cell, means, spreads


@kernel()
def _standardised(
    grid: np.ndarray, cell: np.ndarray, column: np.ndarray, owner: np.ndarray, episode: bool,
    means: np.ndarray, roots: np.ndarray, eps: float,
) -> np.ndarray:  # fmt: skip
    """mask · (c − mean) / (sd + ε) at each packed step (an alive cell: mask 1, and 1 · x = x
    to the bit)."""
    out = np.empty(cell.shape[0], dtype=np.float64)
    for i in range(cell.shape[0]):
        group = column[i] if episode else owner[column[i]]
        out[i] = (grid[cell[i]] - means[group]) / (roots[group] + eps)
    return out


def _option(table: dict[str, int], value: str, name: str) -> int:
    found = table.get(value)
    if found is None:
        raise ValueError(f"{name} must be one of {tuple(table)}, got {value!r}")
    return found


class KernelOptions(NamedTuple):
    """The estimator's options as the kernels take them."""

    gpomdp: bool
    mean_baseline: bool
    from_step: bool
    """Rewards-to-go from the step (discounted from t), else from the start."""
    normalize: int
    weighting: int
    weights: np.ndarray
    """Importance weights as [1, N] (per trajectory) or [T, N] (per decision); empty: none."""

    @property
    def plain(self) -> bool:
        """No standardisation: the coefficients are the grid's (:func:`coefficient_cells`),
        read in place."""
        return self.normalize == _NONE


def kernel_options(options: EstimatorOptions, weights: np.ndarray | None = None) -> KernelOptions:
    """``options`` and ``weights`` (None, [N] or [T, N]) as the kernels take them; ValueError
    for an option outside the names the torch definition knows, or a combination it refuses
    (REINFORCE with ``from_step`` or with per-decision weights)."""
    gpomdp = ESTIMATORS.get(options.estimator).per_step
    mean_baseline = BASELINES.get(options.baseline).subtracts_mean
    from_step = _option(_REWARD_TO_GO, options.reward_to_go, "reward_to_go") == 1
    normalize = _option(_NORMALIZE, options.normalize, "normalize")
    if not gpomdp and from_step:
        raise ValueError("reward_to_go='from_step' needs estimator 'gpomdp'")
    weighting, table = _UNWEIGHTED, _NO_WEIGHTS
    if weights is not None:
        table = np.ascontiguousarray(weights, dtype=np.float64)
        if table.ndim == 1:
            weighting, table = _PER_TRAJECTORY, table.reshape(1, -1)
        elif table.ndim == 2 and gpomdp:
            weighting = _PER_DECISION
        elif table.ndim == 2:
            raise ValueError("REINFORCE takes one importance weight per trajectory")
        else:
            raise ValueError("importance weights are [N] or [T, N]")
    return KernelOptions(gpomdp, mean_baseline, from_step, normalize, weighting, table)


def packed_coefficients(
    options: EstimatorOptions,
    rewards: np.ndarray,
    time: np.ndarray,
    column: np.ndarray,
    lengths: np.ndarray,
    owner: np.ndarray,
    gammas: np.ndarray,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """The estimator's coefficient of each packed step, [R] float64, in the packed order: the
    bits :func:`~fedhpg.common.learning.engine.estimate.batch_coefficients` gives those steps.

    ``rewards`` [R] float64: the steps' rewards, in any order; ``time``, ``column`` [R] int64:
    each step's t and trajectory n (every t < ``lengths[n]`` of every n exactly once);
    ``lengths`` [N] int64 (≥ 1); ``owner`` [N] int64: each trajectory's row, nondecreasing (a
    row may have none); ``gammas`` [A] float64: each row's γ; ``weights``: importance weights,
    None, [N] per trajectory or [T, N] per decision (T ≥ the longest trajectory; the values
    past a trajectory's end, up to its row's longest, count, as in the torch definition).

    Raises ValueError where the torch definition does (REINFORCE with ``from_step`` or with
    per-decision weights), for an option outside the names it knows, and for inputs that are
    not such a batch (the checks cost one pass in the compiled call)."""
    gpomdp, mean_baseline, from_step, normalize, weighting, table = kernel_options(options, weights)
    packed = (
        np.ascontiguousarray(rewards, dtype=np.float64),
        np.ascontiguousarray(time, dtype=np.int64),
        np.ascontiguousarray(column, dtype=np.int64),
        np.ascontiguousarray(lengths, dtype=np.int64),
        np.ascontiguousarray(owner, dtype=np.int64),
        np.ascontiguousarray(gammas, dtype=np.float64),
        table,
    )
    grid, cell, means, spreads = coefficient_cells(
        gpomdp, mean_baseline, from_step, normalize, weighting, *packed
    )
    if normalize == _NONE:
        plain: np.ndarray = grid[cell]
        return plain
    # torch's sqrt on the CPU is MKL's (vdSqrt), which is not always the correctly rounded
    # root (~1 % of float64 inputs one ulp away): the definition's roots are torch's own
    roots = torch.from_numpy(spreads).sqrt().numpy()
    episode = normalize == _EPISODE
    column, owner = packed[2], packed[4]
    standardised: np.ndarray = _standardised(
        grid, cell, column, owner, episode, means, roots, NORMALIZE_EPS
    )
    return standardised
