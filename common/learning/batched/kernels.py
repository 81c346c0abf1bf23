"""The compiled backend's kernels (numba): sampling and score gradients of many agents' MLP
categorical policies on CartPole, an agent at a time.

Why an agent at a time: a tensor backend steps a thousand agents in lockstep to spread each
call over many copies, and pays for it on a CPU: copies whose episode ended wait for their
agent's longest, and a few long episodes carry the per-step cost of dozens of calls. Compiled,
an agent's copies are stepped together (layer by layer over its copies still running, packed
at the front) until its last episode ends, then the next agent's; its weights and activations
stay in L1, and nothing an agent computes can depend on another agent.

Randomness: each copy's draws are common/learning/randomness.py's hash of its trajectory key,
compiled (:func:`uniform24`, :func:`uniform53`): the same numbers as the torch backend's for the
same key and counter.

Numerics:
- sampling and the dynamics are strict IEEE (no ``fastmath``: LLVM may not reassociate or
  contract, so a vectorised loop computes what the scalar one would), so an episode is the
  same on any x86-64 host given θ; ``error_model="numpy"`` everywhere (IEEE division, no zero
  check: the check stops LLVM from vectorising any loop with a division);
- tanh by :func:`tanh32`, a rational function evaluated in float32: a libm ``tanhf`` per unit
  cannot be vectorised, and float32 fills twice the vector lanes of float64. Over every
  float32 in [2⁻³⁰, 10.5], 24 % of its values are one ulp or more off the correctly rounded
  tanh, none more than seven (< 10⁻⁶ relative);
- the gradient summed in float32 over blocks of :data:`BLOCK` rows, the blocks in float64,
  rounded to float32 once, with LLVM free to reorder and fuse the sums within a block
  (:data:`GRADIENT_FASTMATH`): fixed by the compiled code, so the same in any company and
  placement on one CPU type, but hosts of different CPU types may round the gradient
  differently.

Layouts. θ is torch's flat layout (each ``nn.Linear``: weight [out, in] row-major, then
bias). Inside a kernel the weights are padded 3-D arrays indexed by loop variables only (a
computed flat index costs numba a negative-index check per access, which LLVM cannot vectorise
away): ``forward_weights`` [L, w + 1, w] holds layer l's weight as [in, out] with its bias as
the last row (the forward loops over contiguous outputs), ``backward_weights`` [L, w, w] as
[out, in] (the backward loops over contiguous inputs), w the widest layer (for the gradient,
rounded up to :data:`LANES`, the padding zeros).

Reference counts. numba counts a reference, an atomic add, wherever an array variable is bound:
a view (``acts[0]``), an array picked by a condition, an array parameter of a function inlined
into a loop, the arguments of a call to a kernel that calls others. Inside the sampler's time
loop there is none of these (a lone agent's round paid some 2,500 before): its helpers take
whole arrays and the slot to use (:data:`INPUTS`), and are called as leaf functions.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np
from numba import njit, types
from numba.extending import register_jitable

from fedhpg.common.learning import randomness
from fedhpg.envs.compiled import CARTPOLE_STEP_LIMIT, cartpole_step

# tanh(x)/x ≈ P(x²)/Q(x²) on |x| ≤ 10: least squares on the relative error, Chebyshev nodes
_P0 = 0.9999999998560505
_P1 = 0.1406119092512499
_P2 = 0.004375400222555191
_P3 = 4.098167354696576e-05
_P4 = 1.0389412916501332e-07
_P5 = 3.2342311593592774e-11
_Q1 = 0.47394524112148506
_Q2 = 0.029023816398434932
_Q3 = 0.0004911404283108202
_Q4 = 2.4847341405748074e-06
_Q5 = 2.6850501254705975e-09
_P32 = tuple(np.float32(c) for c in (_P0, _P1, _P2, _P3, _P4, _P5))
_Q32 = tuple(np.float32(c) for c in (1.0, _Q1, _Q2, _Q3, _Q4, _Q5))
TANH_CLAMP = np.float32(10.0)
"""|x| at which the rational function's input is clamped (float32 tanh(x) is ±1 from |x| ≈
9.01 on; the clamp keeps the powers of x finite)."""
BLOCK = 64
"""Rows whose gradient is summed in float32 before it joins the float64 total."""
LANES = 16
"""Inputs a layer's sums take in one pass (the gradient's, and the sampler's with many copies
running): a running sum stays in a register across them and is written back once per pass.
Summed through memory term by term (``out[o, r] += w · in[i, r]``), each term waits for the
last one's store."""
NARROW = 4
"""A pass's inputs when at most this many are left (CartPole's observation, a policy's two
logits in the backward pass): a constant count again, without the 12 padding terms of 0 · 0
that a pass of :data:`LANES` would add (the sums, and so every number, are the same)."""
LANES_FROM = 12
"""Running copies from which the sampler's forward takes them as lanes (:func:`forward_lanes`);
below, row by row (:func:`forward`), whose cost grows with the rows where the lanes' does not."""

ACTION, COLUMN, TIME = np.int8, np.int32, np.int16
"""The sampler's packed steps' action (CartPole's two), trajectory (of one call) and time
(under CartPole's 500-step limit) as stored: with the float32 observation, 23 bytes a step
(against 40 in int64), the most of a host's memory in a round of long episodes."""
assert np.iinfo(TIME).max >= CARTPOLE_STEP_LIMIT

F = TypeVar("F", bound=Callable[..., Any])


def kernel(*, inline: bool = False, fastmath: set[str] | None = None) -> Callable[[F], F]:
    """numba's ``njit`` as every kernel here takes it: cached on disk, IEEE division
    (``error_model="numpy"``), strict floats unless ``fastmath`` names the freedoms."""

    def compile_lazily(function: F) -> F:
        return cast(
            F,
            njit(
                cache=True,
                error_model="numpy",
                inline="always" if inline else "never",
                fastmath=fastmath or False,
            )(function),
        )

    return compile_lazily


_clock_gettime: Any = types.ExternalFunction(
    "clock_gettime", types.int32(types.int32, types.voidptr)
)
_THREAD_CLOCK = time.CLOCK_THREAD_CPUTIME_ID


@kernel(inline=True)
def thread_seconds(timespec: np.ndarray) -> float:
    """The calling thread's CPU seconds, the clock ``time.thread_time`` reads (libc's
    ``clock_gettime``, tens of nanoseconds, where numba's object mode would take
    microseconds); ``timespec``: an int64 [2] to read it into."""
    _clock_gettime(_THREAD_CLOCK, timespec.ctypes)
    return timespec[0] + timespec[1] * 1e-9


GRADIENT_FASTMATH = {"reassoc", "contract"}
"""LLVM may reorder and fuse the gradient's sums (vectorised reductions over a block's rows:
about twice the speed of strict order). The order it picks depends on the compiled code
alone, so a host's results never depend on the company an agent keeps; hosts of different CPU
types (AVX-512 against AVX2) may round differently. Sampling and dynamics stay strict. Not
``nsz`` nor ``arcp``: with them a kernel may round differently when just compiled than when
loaded from numba's cache (tests/test_compiled_engine.py checks that it does not)."""


@kernel(inline=True)
def tanh32(value: np.float32) -> np.float32:
    """tanh of a float32, through a rational function evaluated in float32 (see the module
    docstring); NaN stays NaN."""
    x = value
    if x > TANH_CLAMP:
        x = TANH_CLAMP
    elif x < -TANH_CLAMP:
        x = -TANH_CLAMP
    s = x * x
    p = _P32[0] + s * (_P32[1] + s * (_P32[2] + s * (_P32[3] + s * (_P32[4] + s * _P32[5]))))
    q = _Q32[0] + s * (_Q32[1] + s * (_Q32[2] + s * (_Q32[3] + s * (_Q32[4] + s * _Q32[5]))))
    return x * p / q


_mix64 = cast(Callable[[int], int], njit(cache=True, inline="always")(randomness.mix64))
"""common/learning/randomness.py's hash, compiled: the same bits as the engine's torch draws."""
register_jitable(randomness.mix64)  # compiled code calling these compiles the same definitions
register_jitable(randomness.absorb)
_absorb = cast(Callable[[int, int], int], njit(cache=True, inline="always")(randomness.absorb))
_agent_key = cast(
    Callable[[int, int, int, int], int], njit(cache=True, inline="always")(randomness.agent_key)
)
_GOLDEN = randomness.GOLDEN
_TOP24, _TOP53 = (1 << 24) - 1, (1 << 53) - 1


@kernel(inline=True)
def uniform24(key: int, counter: int) -> np.float32:
    """randomness.uniforms(key, counter): a float32 uniform with 24 random bits."""
    z = _mix64(key + (counter + 1) * _GOLDEN)
    return np.float32((z >> 40) & _TOP24) * np.float32(1.0 / (1 << 24))


@kernel(inline=True)
def uniform53(key: int, counter: int) -> float:
    """randomness.uniforms64(key, counter): a float64 uniform with 53 random bits."""
    z = _mix64(key + (counter + 1) * _GOLDEN)
    return float((z >> 11) & _TOP53) * (1.0 / (1 << 53))


@kernel()
def trajectory_keys(
    base: int,
    agents: np.ndarray,
    counts: np.ndarray,
    round_index: int,
    iteration: int,
    out: np.ndarray,
) -> None:
    """randomness.trajectory_keys of ``counts[a]`` trajectories of each agent ``agents[a]``,
    row after row into ``out``."""
    n = 0
    for a in range(agents.shape[0]):
        state = _agent_key(base, agents[a], round_index, iteration)
        for trajectory in range(counts[a]):
            out[n] = _absorb(state, trajectory)
            n += 1


@kernel()
def widest(sizes: np.ndarray) -> int:
    width = 0
    for size in sizes:
        width = max(width, size)
    return width


@kernel()
def fill_weights(
    theta: np.ndarray, sizes: np.ndarray, forward_w: np.ndarray, backward_w: np.ndarray
) -> None:
    """θ (flat, torch's layout) into the padded ``forward_w`` [L, w + 1, w] and
    ``backward_w`` [L, w, w] (module docstring); the padding is left as it is (zeros)."""
    bias_row = forward_w.shape[1] - 1
    offset = 0
    for layer in range(len(sizes) - 1):
        n_in, n_out = sizes[layer], sizes[layer + 1]
        for o in range(n_out):
            for i in range(n_in):
                value = theta[offset + o * n_in + i]
                forward_w[layer, i, o] = value
                backward_w[layer, o, i] = value
            forward_w[layer, bias_row, o] = theta[offset + n_in * n_out + o]
        offset += n_in * n_out + n_out


@kernel()
def padded_width(sizes: np.ndarray) -> int:
    """The widest layer rounded up to :data:`LANES`."""
    return (widest(sizes) + LANES - 1) // LANES * LANES


@kernel()
def padded_weights(theta: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """θ as fresh (forward_weights, backward_weights): module docstring."""
    width = padded_width(sizes)
    forward_w = np.zeros((len(sizes) - 1, width + 1, width), dtype=np.float32)
    backward_w = np.zeros((len(sizes) - 1, width, width), dtype=np.float32)
    fill_weights(theta, sizes, forward_w, backward_w)
    return forward_w, backward_w


INPUTS = 2
"""The slot of an activations array ([3, …]) that holds the inputs: the layers write slots 0
and 1 in turn, the last (the logits) slot 0."""


@kernel(inline=True)
def _slots(layers: int, layer: int) -> tuple[int, int]:
    """The slots layer ``layer`` of ``layers`` reads and writes. Slots, not arrays: numba
    counts a reference (an atomic add) each time an array variable is bound, so a layer loop
    that picked its arrays would pay a few at every layer of every step."""
    written = (layers - 1 - layer) % 2
    return (INPUTS if layer == 0 else 1 - written), written


@kernel()
def dense(weights: np.ndarray, sizes: np.ndarray, layer: int, acts: np.ndarray, rows: int) -> None:
    """Layer ``layer`` of :func:`forward` on the first ``rows`` rows: above[r, :n_out] =
    tanh?(below[r, :n_in] · W + b), ``below`` and ``above`` slots of ``acts`` (:func:`_slots`);
    tanh on every layer but the last."""
    layers = len(sizes) - 1
    below, above = _slots(layers, layer)
    n_in, n_out = sizes[layer], sizes[layer + 1]
    bias_row = weights.shape[1] - 1
    for r in range(rows):
        for o in range(n_out):
            acts[above, r, o] = weights[layer, bias_row, o]
        for i in range(n_in):
            value = acts[below, r, i]
            for o in range(n_out):
                acts[above, r, o] += value * weights[layer, i, o]
    if layer < layers - 1:
        for r in range(rows):
            for o in range(n_out):
                acts[above, r, o] = tanh32(acts[above, r, o])


@kernel()
def forward(weights: np.ndarray, sizes: np.ndarray, acts: np.ndarray, rows: int) -> None:
    """The MLP on the first ``rows`` rows of ``acts[INPUTS]`` (the inputs), tanh between
    layers: the logits end in ``acts[0]`` (``acts``: [3, rows, padded width])."""
    for layer in range(len(sizes) - 1):
        dense(weights, sizes, layer, acts, rows)


@kernel()
def dense_lanes(
    weights: np.ndarray, sizes: np.ndarray, layer: int, lanes: np.ndarray, chunks: int
) -> None:
    """:func:`dense` on columns: above[k, o, c] = tanh?(b_o + Σ_i W[i, o] · below[k, i, c]) for
    the first ``chunks`` chunks of :data:`LANES` columns ([chunk, unit, lane], a lane a copy;
    ``below`` and ``above`` slots of ``lanes``). The terms are added in input order after the
    bias, each rounded as :func:`dense` rounds it (strict IEEE), so a column is exactly what
    :func:`dense` gives that row; the padding inputs add 0 · 0 (``above``'s padding units are
    zeroed for the layer above). The lanes are a constant count at a constant offset, which is
    what lets LLVM keep the sums in registers."""
    layers = len(sizes) - 1
    below, above = _slots(layers, layer)
    n_in, n_out = sizes[layer], sizes[layer + 1]
    bias_row = weights.shape[1] - 1
    for k in range(chunks):
        for first in range(0, n_in, LANES):
            narrow = n_in - first <= NARROW  # the terms left out add 0 · 0: the same sums
            for o in range(n_out):
                bias = weights[layer, bias_row, o]
                if narrow:
                    for c in range(LANES):
                        value = bias if first == 0 else lanes[above, k, o, c]
                        for i in range(NARROW):
                            value += weights[layer, first + i, o] * lanes[below, k, first + i, c]
                        lanes[above, k, o, c] = value
                else:
                    for c in range(LANES):
                        value = bias if first == 0 else lanes[above, k, o, c]
                        for i in range(LANES):
                            value += weights[layer, first + i, o] * lanes[below, k, first + i, c]
                        lanes[above, k, o, c] = value
        if layer < layers - 1:
            for o in range(n_out):
                for c in range(LANES):
                    lanes[above, k, o, c] = tanh32(lanes[above, k, o, c])
        for o in range(n_out, (n_out + LANES - 1) // LANES * LANES):
            for c in range(LANES):
                lanes[above, k, o, c] = 0.0


@kernel()
def forward_lanes(weights: np.ndarray, sizes: np.ndarray, lanes: np.ndarray, columns: int) -> None:
    """:func:`forward` on the first ``columns`` columns of ``lanes[INPUTS]`` ([chunk, feature,
    lane], zero past the input's features; the weights padded to :data:`LANES` units): the
    logits end in ``lanes[0]``."""
    for layer in range(len(sizes) - 1):
        dense_lanes(weights, sizes, layer, lanes, (columns + LANES - 1) // LANES)


@kernel()
def draw_action(acts: np.ndarray, row: int, n_actions: int, uniform: float | np.float32,
                scratch: np.ndarray) -> int:  # fmt: skip
    """Inverse-CDF categorical draw (common/learning/policies.py's ``categorical_act``) from
    row ``row`` of the logits ``acts[0]`` (:func:`forward`'s; indexed, not sliced: a view
    would count a reference at every step)."""
    best = 0
    for j in range(1, n_actions):
        if acts[0, row, j] > acts[0, row, best]:
            best = j
    top = acts[0, row, best]
    total = np.float32(0.0)
    for j in range(n_actions):
        # exp(0) is exactly 1: the largest logit's term needs no call
        scratch[j] = np.float32(1.0) if j == best else np.float32(math.exp(acts[0, row, j] - top))
        total += scratch[j]
    threshold = uniform * total
    cumulative = np.float32(0.0)
    action = 0
    for j in range(n_actions - 1):
        cumulative += scratch[j]
        if threshold > cumulative:
            action += 1
    return action


@kernel()
def greedy_action(acts: np.ndarray, row: int, n_actions: int) -> int:
    """The most likely action of row ``row`` of the logits ``acts[0]``."""
    best = 0
    for j in range(1, n_actions):
        if acts[0, row, j] > acts[0, row, best]:
            best = j
    return best


@kernel()
def rollout_workspace(sizes: np.ndarray, copies: int) -> tuple[np.ndarray, ...]:
    """Scratch for :func:`rollout_agent` of up to ``copies`` copies (made once per call of a
    whole iteration, not per agent: at ~20-step episodes an agent's own allocations cost more
    than its steps)."""
    width = padded_width(sizes)
    chunks = (copies + LANES - 1) // LANES
    return (
        np.zeros((len(sizes) - 1, width + 1, width), dtype=np.float32),  # forward weights
        np.zeros((len(sizes) - 1, width, width), dtype=np.float32),  # backward weights
        np.zeros((3, copies, width), dtype=np.float32),  # inputs and activations (slots)
        np.zeros(sizes[len(sizes) - 1], dtype=np.float32),  # the draw's exponentials
        np.zeros((copies, 4), dtype=np.float64),  # CartPole states
        np.zeros(copies, dtype=np.int64),  # the copies still running
        np.zeros((3, chunks, width, LANES), dtype=np.float32),  # the same as lanes
    )


@kernel()
def rollout_agent(
    theta: np.ndarray,
    sizes: np.ndarray,
    physics: np.ndarray,
    keys: np.ndarray,
    first_copy: int,
    copies: int,
    horizon: int,
    greedy: bool,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_column: np.ndarray,
    rows_time: np.ndarray,
    first_row: int,
    lengths: np.ndarray,
    workspace: tuple[np.ndarray, ...],
) -> int:
    """One CartPole episode in each of ``copies`` copies of one agent's variant from θ: copy c
    is column ``first_copy + c`` with trajectory key ``keys[first_copy + c]``.

    Writes the rows (observation, action, column, step) of every alive step from ``first_row``
    on, time-major, and each column's length. Returns the row after the last written. Every
    draw is the copy's own (common/learning/randomness.py's hash of its key): the start's four
    uniforms from counters −1 … −4, the decision at step t from counter t."""
    weights, backward_w, acts, scratch, state, running, lanes = workspace
    obs_dim = sizes[0]
    n_actions = sizes[len(sizes) - 1]
    fill_weights(theta, sizes, weights, backward_w)
    for c in range(copies):
        key = keys[first_copy + c]
        for i in range(4):
            state[c, i] = uniform53(key, -1 - i) * 0.1 - 0.05
        running[c] = c  # the copies still running, in copy order
    alive = copies
    limit = min(horizon, CARTPOLE_STEP_LIMIT)
    row = first_row
    for t in range(limit):
        # forward's layers in line: a call of forward would count references at every step
        if alive >= LANES_FROM:
            for slot in range(alive):
                for i in range(obs_dim):
                    value = np.float32(state[running[slot], i])
                    acts[INPUTS, slot, i] = value
                    lanes[INPUTS, slot // LANES, i, slot % LANES] = value
            for layer in range(len(sizes) - 1):
                dense_lanes(weights, sizes, layer, lanes, (alive + LANES - 1) // LANES)
            for slot in range(alive):  # the same numbers as rows, for the draw
                for j in range(n_actions):
                    acts[0, slot, j] = lanes[0, slot // LANES, j, slot % LANES]
        else:
            for slot in range(alive):
                for i in range(obs_dim):
                    acts[INPUTS, slot, i] = np.float32(state[running[slot], i])
            for layer in range(len(sizes) - 1):
                dense(weights, sizes, layer, acts, alive)
        kept = 0
        for slot in range(alive):
            c = running[slot]
            if greedy:
                action = greedy_action(acts, slot, n_actions)
            else:
                draw = uniform24(keys[first_copy + c], t)
                action = draw_action(acts, slot, n_actions, draw, scratch)
            for i in range(obs_dim):
                rows_obs[row, i] = acts[INPUTS, slot, i]
            rows_action[row] = action
            rows_column[row] = first_copy + c
            rows_time[row] = t
            row += 1
            terminated = cartpole_step(state, c, physics, action)
            if terminated or t + 1 >= limit:
                lengths[first_copy + c] = t + 1
            else:
                running[kept] = c
                kept += 1
        alive = kept
        if alive == 0:
            break
    return row


@kernel()
def sample_rows(
    thetas: np.ndarray,
    sizes: np.ndarray,
    physics: np.ndarray,
    counts: np.ndarray,
    horizons: np.ndarray,
    keys: np.ndarray,
    greedy: bool,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_column: np.ndarray,
    rows_time: np.ndarray,
    lengths: np.ndarray,
) -> int:
    """Row a's ``counts[a]`` episodes from θ_a = ``thetas[a]`` (its copies the next
    ``counts[a]`` columns, their keys ``keys``), agent after agent; returns the rows written."""
    most = 1
    for count in counts:
        most = max(most, count)
    workspace = rollout_workspace(sizes, most)
    row = 0
    column = 0
    for a in range(len(counts)):
        row = rollout_agent(thetas[a], sizes, physics[a], keys, column, counts[a], horizons[a],
                            greedy, rows_obs, rows_action, rows_column, rows_time, row, lengths,
                            workspace)  # fmt: skip
        column += counts[a]
    return row


@kernel(inline=True)
def _zero_rows(rows: np.ndarray, first: int) -> None:
    """rows[first:] = 0: a layer's padding units, which a pass of :data:`LANES` reads."""
    for j in range(first, rows.shape[0]):
        for r in range(rows.shape[1]):
            rows[j, r] = 0.0


@kernel()
def gradient_workspace(sizes: np.ndarray) -> tuple[np.ndarray, ...]:
    """Scratch for :func:`score_gradient`, made once per iteration's call: units padded to
    a multiple of :data:`LANES` with zeros (weights, activations and δ of no unit)."""
    layers = len(sizes) - 1
    width = widest(sizes)
    padded = padded_width(sizes)
    return (
        np.zeros((layers, padded + 1, padded), dtype=np.float32),  # forward weights
        np.zeros((layers, padded, padded), dtype=np.float32),  # backward weights
        np.zeros((layers + 1, padded, BLOCK), dtype=np.float32),  # activations
        np.zeros((padded, BLOCK), dtype=np.float32),  # δ
        np.zeros((padded, BLOCK), dtype=np.float32),  # a layer's sums: Wx + b, then Wᵀδ
        np.zeros(BLOCK, dtype=np.float32),  # the largest logit per row
        np.zeros(BLOCK, dtype=np.float32),  # the softmax's normaliser per row
        np.zeros((layers, width, width), dtype=np.float64),  # weight gradient
        np.zeros((layers, width), dtype=np.float64),  # bias gradient
        np.zeros(BLOCK, dtype=np.float32),  # the block's coefficients
        np.zeros(BLOCK, dtype=np.float32),  # the block's actions (as floats: one tuple type)
        np.ones(BLOCK, dtype=np.float32),  # ones: a bias's inputs
    )


@kernel(fastmath=GRADIENT_FASTMATH)
def score_gradient(
    theta: np.ndarray,
    sizes: np.ndarray,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_coef: np.ndarray,
    rows_cell: np.ndarray,
    low: int,
    high: int,
    out: np.ndarray,
    workspace: tuple[np.ndarray, ...],
) -> None:
    """out (float32, flat θ layout) = Σ_{r ∈ [low, high)} coef_r · ∇_θ log π(a_r|s_r), row
    r's coefficient ``rows_coef[rows_cell[r]]`` rounded to float32.

    Blocks of :data:`BLOCK` rows, feature-major (a layer's activations are [unit, row], so
    every loop runs along the block's rows: long and contiguous, where row-major loops along
    16 units cost LLVM more in loop entries than in arithmetic); each block's sums over its
    rows are added to float64 totals."""
    forward_w, backward_w, acts, delta, below, top, total = workspace[:7]
    weight_total, bias_total, coef, action, ones = workspace[7:]
    layers = len(sizes) - 1
    n_actions = sizes[layers]
    fill_weights(theta, sizes, forward_w, backward_w)
    weight_total[:] = 0.0
    bias_total[:] = 0.0
    for start in range(low, high, BLOCK):
        # every block is BLOCK rows long, a short last one padded with zero rows whose
        # coefficient is 0 (they add exact zeros): loops of a constant length compile to
        # straight vector code, without the remainder loops a variable length needs
        rows = min(BLOCK, high - start)
        for i in range(sizes[0]):
            for r in range(rows):
                acts[0, i, r] = rows_obs[start + r, i]
            for r in range(rows, BLOCK):
                acts[0, i, r] = 0.0
        for r in range(rows):
            coef[r] = np.float32(rows_coef[rows_cell[start + r]])
            action[r] = np.float32(rows_action[start + r])
        for r in range(rows, BLOCK):
            coef[r] = 0.0
            action[r] = 0
        bias_row = forward_w.shape[1] - 1
        for layer in range(layers):
            n_in, n_out = sizes[layer], sizes[layer + 1]
            # The sums go to ``below``, not to the next layer's rows of ``acts``: LLVM cannot
            # tell two rows of one array apart, and would not keep a row's sum in a register.
            for first in range(0, n_in, LANES):  # padded inputs: zero weights, zero units
                narrow = n_in - first <= NARROW
                for o in range(n_out):
                    bias = forward_w[layer, bias_row, o]
                    if narrow:
                        for r in range(BLOCK):
                            value = bias if first == 0 else below[o, r]
                            for i in range(NARROW):
                                value += forward_w[layer, first + i, o] * acts[layer, first + i, r]
                            below[o, r] = value
                    else:
                        for r in range(BLOCK):
                            value = bias if first == 0 else below[o, r]
                            for i in range(LANES):
                                value += forward_w[layer, first + i, o] * acts[layer, first + i, r]
                            below[o, r] = value
            for o in range(n_out):
                if layer < layers - 1:
                    for r in range(BLOCK):
                        acts[layer + 1, o, r] = tanh32(below[o, r])
                else:
                    for r in range(BLOCK):
                        acts[layer + 1, o, r] = below[o, r]
        # ∂ log π(a|s) / ∂ logits = onehot(a) − π, times the row's coefficient
        for r in range(BLOCK):
            top[r] = acts[layers, 0, r]
            total[r] = 0.0
        for j in range(1, n_actions):
            for r in range(BLOCK):
                top[r] = max(top[r], acts[layers, j, r])
        for j in range(n_actions):
            for r in range(BLOCK):
                delta[j, r] = np.float32(math.exp(acts[layers, j, r] - top[r]))
                total[r] += delta[j, r]
        for j in range(n_actions):
            for r in range(BLOCK):
                hit = np.float32(1.0) if np.float32(j) == action[r] else np.float32(0.0)
                delta[j, r] = (hit - delta[j, r] / total[r]) * coef[r]
        _zero_rows(delta, n_actions)
        for layer in range(layers - 1, -1, -1):
            n_in, n_out = sizes[layer], sizes[layer + 1]
            for o in range(n_out):
                block_sum = np.float32(0.0)
                for r in range(BLOCK):  # times ones: a plain sum compiled to a serial chain
                    block_sum += delta[o, r] * ones[r]
                bias_total[layer, o] += block_sum
                for i in range(n_in):
                    block_sum = np.float32(0.0)
                    for r in range(BLOCK):
                        block_sum += delta[o, r] * acts[layer, i, r]
                    weight_total[layer, o, i] += block_sum
            if layer > 0:  # δ below = (Wᵀ δ) ⊙ tanh', tanh' = 1 − h²
                for first in range(0, n_out, LANES):  # δ's padding rows are zeros
                    narrow = n_out - first <= NARROW
                    for i in range(n_in):
                        if narrow:
                            for r in range(BLOCK):
                                value = np.float32(0.0) if first == 0 else below[i, r]
                                for o in range(NARROW):
                                    value += backward_w[layer, first + o, i] * delta[first + o, r]
                                below[i, r] = value
                        else:
                            for r in range(BLOCK):
                                value = np.float32(0.0) if first == 0 else below[i, r]
                                for o in range(LANES):
                                    value += backward_w[layer, first + o, i] * delta[first + o, r]
                                below[i, r] = value
                for i in range(n_in):
                    for r in range(BLOCK):
                        h = acts[layer, i, r]
                        delta[i, r] = below[i, r] * (np.float32(1.0) - h * h)
                _zero_rows(delta, n_in)
    offset = 0
    for layer in range(layers):
        n_in, n_out = sizes[layer], sizes[layer + 1]
        for o in range(n_out):
            for i in range(n_in):
                out[offset + o * n_in + i] = np.float32(weight_total[layer, o, i])
            out[offset + n_in * n_out + o] = np.float32(bias_total[layer, o])
        offset += n_in * n_out + n_out


@kernel()
def row_gradients(
    thetas: np.ndarray,
    sizes: np.ndarray,
    rows_obs: np.ndarray,
    rows_action: np.ndarray,
    rows_coef: np.ndarray,
    rows_cell: np.ndarray,
    row_start: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[a] = Σ_{r ∈ row a's steps} coef_r · ∇_θ log π_θa(a_r|s_r), row a's steps being
    ``row_start[a]`` … ``row_start[a + 1]`` − 1 and step r's coefficient
    ``rows_coef[rows_cell[r]]`` (the engine's ``gradients`` primitive)."""
    workspace = gradient_workspace(sizes)
    for a in range(thetas.shape[0]):
        score_gradient(thetas[a], sizes, rows_obs, rows_action, rows_coef, rows_cell,
                       row_start[a], row_start[a + 1], out[a], workspace)  # fmt: skip
