"""The compiled backend's fused calls: a sample with the keys it is drawn from; mean
gradients with the estimator's coefficients; and both at once, agent by agent.

Each calls the kernels the separate steps would (``trajectory_keys``, ``rollout_agent`` and
``row_gradients`` of :mod:`~fedhpg.common.learning.batched.kernels`, and
:func:`~fedhpg.common.learning.batched.estimator.coefficient_cells`) on the same numbers in the
same order, so its numbers are theirs, bit for bit (``tests/test_compiled_fused.py``). What
the first two save is the Python between those kernels, which a lone agent's round otherwise
pays at every iteration. :func:`sampled_gradients` saves memory and memory traffic as well: it
draws a few agents' trajectories into arrays of some :data:`CHUNK_STEPS` steps and takes their
gradients while those steps are in the cache, so a host's iteration never holds every agent's
steps at once (23 bytes a step, and 17 more for the estimator's grid). It reads the thread's
CPU clock around each chunk's sampling, so each agent's time still splits between sampling and
gradients as the round reports it (``engine_sample_s``, ``engine_gradient_s``).
"""

from __future__ import annotations

import numpy as np

from fedhpg.common.learning.batched.estimator import NO_STANDARDISATION, coefficient_cells
from fedhpg.common.learning.batched.kernels import (
    kernel,
    rollout_agent,
    rollout_workspace,
    row_gradients,
    sample_rows,
    thread_seconds,
    trajectory_keys,
)

CHUNK_STEPS = 8192
"""Steps :func:`sampled_gradients` draws before it takes their gradients (an agent's
trajectories are never split): with their estimator's cells about half a MiB, which stays in
a core's L2 cache."""


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
    _divided(gradients, trajectories)


@kernel(inline=True)
def _divided(gradients: np.ndarray, trajectories: np.ndarray) -> None:
    """Each row of sums divided by its trajectories (at least 1) in float32, as torch
    divides."""
    for a in range(gradients.shape[0]):
        divisor = np.float32(max(trajectories[a], 1))
        for j in range(gradients.shape[1]):
            gradients[a, j] = gradients[a, j] / divisor


@kernel()
def _draw_chunk(
    thetas: np.ndarray,
    sizes: np.ndarray,
    physics: np.ndarray,
    counts: np.ndarray,
    horizons: np.ndarray,
    greedy: bool,
    keys: np.ndarray,
    first_row: int,
    first_column: int,
    chunk_steps: int,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_column: np.ndarray,
    rows_time: np.ndarray,
    lengths: np.ndarray,
    workspace: tuple[np.ndarray, ...],
) -> tuple[int, int]:
    """Rows from ``first_row`` on drawn (as :func:`sample_rows` draws them, the chunk's
    columns from 0) until ``chunk_steps`` steps are written; returns (the row after the
    last drawn, the steps written)."""
    a, column, written = first_row, first_column, 0
    while a < counts.shape[0] and (a == first_row or written < chunk_steps):
        written = rollout_agent(thetas[a], sizes, physics[a], keys[first_column:],
                                column - first_column, counts[a], horizons[a], greedy, rows_obs,
                                rows_action, rows_column, rows_time, written,
                                lengths[first_column:], workspace)  # fmt: skip
        column += counts[a]
        a += 1
    return a, written


@kernel()
def chunk_capacity(counts: np.ndarray, horizons: np.ndarray, chunk_steps: int) -> int:
    """The most steps :func:`sampled_gradients` writes into its chunk's arrays: a chunk
    stops once it holds ``chunk_steps``, so at most that less one, and one more row's."""
    widest = 0
    for a in range(counts.shape[0]):
        widest = max(widest, counts[a] * horizons[a])
    return chunk_steps + widest


@kernel()
def sampled_gradients(
    run_key: int,
    agents: np.ndarray,
    round_word: int,
    iteration_word: int,
    sample_thetas: np.ndarray,
    thetas: np.ndarray,
    sizes: np.ndarray,
    physics: np.ndarray,
    counts: np.ndarray,
    horizons: np.ndarray,
    greedy: bool,
    gpomdp: bool,
    mean_baseline: bool,
    from_step: bool,
    weights: np.ndarray,
    gammas: np.ndarray,
    chunk_steps: int,
    rewards: np.ndarray,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_column: np.ndarray,
    rows_time: np.ndarray,
    lengths: np.ndarray,
    owner: np.ndarray,
    row_start: np.ndarray,
    gradients: np.ndarray,
) -> tuple[int, float]:
    """:func:`keyed_sample` at ``sample_thetas`` then :func:`estimated_gradients` at
    ``thetas`` (unweighted), a chunk of rows at a time: rows are drawn (an agent's
    ``counts[a]`` ≥ 1 episodes at once) until some ``chunk_steps`` steps are written, then the
    chunk's coefficients and gradients are taken, and its steps dropped. ``lengths``,
    ``owner`` and ``row_start`` come out as :func:`keyed_sample` writes them, ``gradients``
    [A, d] as :func:`estimated_gradients` does, every number the same (each row's numbers
    use its own steps alone). A chunk's steps go to ``rows_*`` (room for
    :func:`chunk_capacity` steps, the caller's to reuse from call to call: allocated afresh,
    their pages would be faulted in again every call), each with a reward of ``rewards``
    (CartPole's 1: a view of one number). Returns (the steps drawn, the thread CPU seconds
    spent drawing them)."""
    rows, columns = counts.shape[0], lengths.shape[0]
    keys = np.empty(columns, dtype=np.int64)
    trajectory_keys(run_key, agents, counts, round_word, iteration_word, keys)
    if rows_obs.shape[0] < chunk_capacity(counts, horizons, chunk_steps):
        raise ValueError("the chunk's arrays are too small")
    most = 1
    for a in range(rows):
        most = max(most, counts[a])
    workspace = rollout_workspace(sizes, most)
    timespec = np.empty(2, dtype=np.int64)
    sampling = 0.0
    drawn = 0
    row_start[0] = 0
    a = 0
    column = 0
    while a < rows:
        first_row, first_column = a, column
        started = thread_seconds(timespec)
        a, written = _draw_chunk(sample_thetas, sizes, physics, counts, horizons, greedy, keys,
                                 first_row, first_column, chunk_steps, rows_obs, rows_action,
                                 rows_column, rows_time, lengths, workspace)  # fmt: skip
        for row in range(first_row, a):
            column += counts[row]
        ended = thread_seconds(timespec)
        sampling += ended - started
        chunk_owner = np.empty(column - first_column, dtype=np.int64)
        chunk_start = np.empty(a - first_row + 1, dtype=np.int64)
        chunk_start[0] = 0
        n = first_column
        for row in range(first_row, a):
            for _ in range(counts[row]):
                chunk_owner[n - first_column] = row - first_row
                owner[n] = row
                drawn += lengths[n]
                n += 1
            row_start[row + 1] = drawn
            chunk_start[row - first_row + 1] = drawn - row_start[first_row]
        grid, cell, _, _ = coefficient_cells(gpomdp, mean_baseline, from_step, NO_STANDARDISATION,
                                             0, rewards[:written], rows_time[:written],
                                             rows_column[:written], lengths[first_column:column],
                                             chunk_owner, gammas[first_row:a],
                                             weights)  # fmt: skip
        row_gradients(thetas[first_row:a], sizes, rows_obs, rows_action, grid, cell, chunk_start,
                      gradients[first_row:a])  # fmt: skip
        _divided(gradients[first_row:a], counts[first_row:a])
    return drawn, sampling
