"""The compiled backend's two calls a local iteration: its sample with the keys it is drawn
from, and its mean gradients with the estimator's coefficients.

Each calls the kernels the separate steps would (``trajectory_keys``, ``sample_rows`` and
``row_gradients`` of :mod:`~fedhpg.common.learning.batched.kernels`, and
:func:`~fedhpg.common.learning.batched.estimator.coefficient_cells`) on the same arrays in the same
order, so its numbers are theirs, bit for bit (``tests/test_compiled_fused.py``). What it
saves is the Python between them (wrapping each call's arrays as tensors and back), which a
lone agent's round otherwise pays at every iteration. The sampling and the gradient stay two
calls so that each agent's time splits between them as the round reports it
(``engine_sample_s``, ``engine_gradient_s``).
"""

from __future__ import annotations

import numpy as np

from fedhpg.common.learning.batched.estimator import NO_STANDARDISATION, coefficient_cells
from fedhpg.common.learning.batched.kernels import (
    kernel,
    row_gradients,
    sample_rows,
    trajectory_keys,
)


@kernel()
def keyed_sample(
    run_key: int,
    agents: np.ndarray,
    round_word: int,
    iteration_word: int,
    thetas: np.ndarray,
    sizes: np.ndarray,
    physics: np.ndarray,
    counts: np.ndarray,
    horizons: np.ndarray,
    greedy: bool,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_column: np.ndarray,
    rows_time: np.ndarray,
    lengths: np.ndarray,
    owner: np.ndarray,
    row_start: np.ndarray,
) -> int:
    """Row a's ``counts[a]`` ≥ 1 episodes from θ_a = ``thetas[a]``, keyed as
    :func:`~fedhpg.common.learning.batched.kernels.trajectory_keys` keys agent ``agents[a]``'s and
    written as :func:`~fedhpg.common.learning.batched.kernels.sample_rows` writes them; each
    trajectory's row into ``owner`` [N], each row's first packed step into ``row_start``
    [A + 1]; returns the steps written."""
    keys = np.empty(lengths.shape[0], dtype=np.int64)
    trajectory_keys(run_key, agents, counts, round_word, iteration_word, keys)
    written: int = sample_rows(thetas, sizes, physics, counts, horizons, keys, greedy, rows_obs,
                               rows_action, rows_column, rows_time, lengths)  # fmt: skip
    n = 0
    step = 0
    row_start[0] = 0
    for a in range(counts.shape[0]):
        for _ in range(counts[a]):
            owner[n] = a
            step += lengths[n]
            n += 1
        row_start[a + 1] = step
    return written


@kernel()
def estimated_gradients(
    gpomdp: bool,
    mean_baseline: bool,
    from_step: bool,
    weighting: int,
    weights: np.ndarray,
    gammas: np.ndarray,
    rows_time: np.ndarray,
    rows_column: np.ndarray,
    lengths: np.ndarray,
    owner: np.ndarray,
    rewards: np.ndarray,
    thetas: np.ndarray,
    sizes: np.ndarray,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    row_start: np.ndarray,
    gradients: np.ndarray,
) -> None:
    """(1/B_a) Σ_n Σ_t coef_t,n ∇ log π_θa(a_t|s_t) over row a's B_a trajectories into
    ``gradients[a]``: the unstandardised estimator's coefficients of the packed steps, one
    reward of ``rewards`` each (CartPole's: a view of one 1.0, no array a step),
    the score gradients at ``thetas``, then each row's sum divided by its trajectories in
    float32, as torch divides."""
    written = rewards.shape[0]
    # the coefficients read where the estimator puts them (step r's: grid[cell[r]]), not
    # gathered into an array a step: at a host's million steps, two arrays fewer
    grid, cell, _, _ = coefficient_cells(gpomdp, mean_baseline, from_step, NO_STANDARDISATION,
                                         weighting, rewards, rows_time[:written],
                                         rows_column[:written], lengths, owner, gammas,
                                         weights)  # fmt: skip
    row_gradients(thetas, sizes, rows_obs, rows_action, grid, cell, row_start, gradients)
    trajectories = np.zeros(gradients.shape[0], dtype=np.int64)
    for n in range(owner.shape[0]):
        trajectories[owner[n]] += 1
    for a in range(gradients.shape[0]):
        divisor = np.float32(max(trajectories[a], 1))
        for j in range(gradients.shape[1]):
            gradients[a, j] = gradients[a, j] / divisor
