"""The tanh MLP categorical policy of many agents at once, each with its own θ.

Forward (sampling) and the score-function gradient (1/B) Σ coef · ∇ log π(a|s) in numpy,
written so that an agent's numbers never depend on which other agents share the batch:

- Every matrix product is one stacked ``np.matmul`` in which each agent (or each chunk of an
  agent's rows) is its own matrix, so BLAS sees the same shapes whatever the batch holds; a
  row of a product does not depend on the other rows (checked in tests/test_batched_engine.py).
- Elementwise operations (tanh, exp, the softmax) are exact per lane.
- The one reduction across an agent's rows — the weight gradient Σ_rows hᵀ·δ — is done per
  chunk of ``CHUNK_ROWS`` rows (one fixed-size product each), then the chunks are added in
  order with plain additions. Zero-padding a chunk adds exact zeros.

The flat θ layout is torch's: for each ``nn.Linear`` its weight [out, in] row-major, then
its bias [out], layer after layer (common/policies.py's MLPCategoricalPolicy).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

CHUNK_ROWS = 64
"""Rows per chunk of the gradient's reduction."""


@dataclass(frozen=True)
class MLPShape:
    """Layer sizes [obs_dim, *hidden, num_actions] of the flat parameter vector."""

    sizes: tuple[int, ...]

    @property
    def layers(self) -> list[tuple[int, int, int]]:
        """(offset, in, out) of each layer's weight; its bias follows the weight."""
        out, offset = [], 0
        for n_in, n_out in itertools.pairwise(self.sizes):
            out.append((offset, n_in, n_out))
            offset += n_in * n_out + n_out
        return out

    @property
    def num_params(self) -> int:
        return sum(n_in * n_out + n_out for _, n_in, n_out in self.layers)


Layers = list[tuple[np.ndarray, np.ndarray]]
"""Per layer: weights [A, in, out] and biases [A, 1, out], float32, C-contiguous."""


def unflatten(shape: MLPShape, theta: np.ndarray) -> Layers:
    """Per-agent layers from θ [A, d] (copies: the caller may change θ afterwards)."""
    layers = []
    for offset, n_in, n_out in shape.layers:
        weight = theta[:, offset : offset + n_in * n_out].reshape(-1, n_out, n_in)
        bias = theta[:, offset + n_in * n_out : offset + n_in * n_out + n_out]
        layers.append((np.ascontiguousarray(weight.transpose(0, 2, 1)), bias[:, None, :].copy()))
    return layers


def select(layers: Layers, rows: np.ndarray | slice) -> Layers:
    return [(w[rows], b[rows]) for w, b in layers]


def forward(layers: Layers, x: np.ndarray) -> list[np.ndarray]:
    """Activations [h_0 = x, h_1, …, logits] for inputs x [A, n, in] (float32)."""
    activations = [x]
    for i, (weight, bias) in enumerate(layers):
        h = np.matmul(activations[-1], weight)
        h += bias
        if i < len(layers) - 1:
            np.tanh(h, out=h)
        activations.append(h)
    return activations


def logits(layers: Layers, x: np.ndarray) -> np.ndarray:
    return forward(layers, x)[-1]


def draw_actions(logit: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """Categorical draws [N] by inverting each row's CDF with one uniform (the last action is
    never exceeded, whatever the rounding). Column by column: a handful of actions, many rows."""
    columns = logit.shape[-1]
    top = logit[:, 0].copy()
    for j in range(1, columns):
        np.maximum(top, logit[:, j], out=top)
    cumulative = np.empty((columns, len(logit)), dtype=logit.dtype)
    np.exp(logit[:, 0] - top, out=cumulative[0])
    for j in range(1, columns):
        np.exp(logit[:, j] - top, out=cumulative[j])
        cumulative[j] += cumulative[j - 1]
    thresholds = uniforms * cumulative[-1]
    actions = np.zeros(len(logit), dtype=np.int64)
    for j in range(columns - 1):
        actions += thresholds > cumulative[j]
    return actions


@dataclass(frozen=True)
class Chunks:
    """The alive rows of A agents packed into chunks of ``CHUNK_ROWS`` rows, agent by agent:
    agent a's chunks are ``first[a] … first[a] + count[a] − 1``, its rows in their sampled
    order. Padding rows (the end of an agent's last chunk) have coefficient 0."""

    obs: np.ndarray  # [C, R, in] float32
    actions: np.ndarray  # [C, R] int64
    coef: np.ndarray  # [C, R] float32
    owner: np.ndarray  # [C]
    first: np.ndarray  # [A]
    count: np.ndarray  # [A]


def pack_rows(
    agent_of_row: np.ndarray,
    obs: np.ndarray,
    actions: np.ndarray,
    coef: np.ndarray,
    num_agents: int,
) -> Chunks:
    """Pack rows (already in agent-then-time order; ``agent_of_row`` non-decreasing)."""
    rows = np.bincount(agent_of_row, minlength=num_agents)
    count = np.maximum(-(-rows // CHUNK_ROWS), 1)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    row_start = np.concatenate([[0], np.cumsum(rows)[:-1]])
    position = np.arange(len(agent_of_row)) - row_start[agent_of_row]
    chunk = first[agent_of_row] + position // CHUNK_ROWS
    slot = position % CHUNK_ROWS
    total = int(count.sum())
    packed_obs = np.zeros((total, CHUNK_ROWS, obs.shape[-1]), dtype=np.float32)
    packed_actions = np.zeros((total, CHUNK_ROWS), dtype=np.int64)
    packed_coef = np.zeros((total, CHUNK_ROWS), dtype=np.float32)
    packed_obs[chunk, slot] = obs
    packed_actions[chunk, slot] = actions
    packed_coef[chunk, slot] = coef
    owner = np.repeat(np.arange(num_agents), count)
    return Chunks(packed_obs, packed_actions, packed_coef, owner, first, count)


def _log_softmax_grad(logit: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """∂ log π(a|s) / ∂ logits = onehot(a) − π, column by column (few actions, many rows)."""
    columns = logit.shape[-1]
    top = logit[..., 0].copy()
    for j in range(1, columns):
        np.maximum(top, logit[..., j], out=top)
    weights = np.empty(logit.shape, dtype=logit.dtype)
    total = np.zeros(top.shape, dtype=logit.dtype)
    for j in range(columns):
        np.exp(logit[..., j] - top, out=weights[..., j])
        total += weights[..., j]
    weights /= -total[..., None]
    for j in range(columns):
        weights[..., j] += actions == j
    return weights


CACHE_CHUNKS = 128
"""Chunks whose activations are worked on together (~0.5 MB each: they stay in cache)."""


def score_gradient(shape: MLPShape, layers: Layers, chunks: Chunks) -> np.ndarray:
    """Σ_rows coef · ∇_θ log π(a|s) per agent, [A, d] float32 in the flat θ layout."""
    num_chunks = len(chunks.owner)
    parts = np.empty((num_chunks, shape.num_params), dtype=np.float32)
    for start in range(0, num_chunks, CACHE_CHUNKS):
        block = slice(start, min(start + CACHE_CHUNKS, num_chunks))
        _chunk_gradients(
            shape,
            select(layers, chunks.owner[block]),
            chunks.obs[block],
            chunks.actions[block],
            chunks.coef[block],
            parts[block],
        )
    # each agent's chunks added in order (plain additions: the same sums in any company)
    gradient = parts[chunks.first].copy()
    for j in range(1, int(chunks.count.max())):
        agents = np.nonzero(chunks.count > j)[0]
        gradient[agents] += parts[chunks.first[agents] + j]
    return gradient


def _chunk_gradients(
    shape: MLPShape,
    per_chunk: Layers,
    obs: np.ndarray,
    actions: np.ndarray,
    coef: np.ndarray,
    parts: np.ndarray,
) -> None:
    """Each chunk's Σ_rows coef · ∇_θ log π(a|s), written into ``parts`` [C, d]."""
    num_chunks = len(obs)
    activations = forward(per_chunk, obs)
    delta = _log_softmax_grad(activations[-1], actions)
    delta *= coef[..., None]
    ones = np.ones((num_chunks, 1, CHUNK_ROWS), dtype=np.float32)
    for i in reversed(range(len(per_chunk))):
        offset, n_in, n_out = shape.layers[i]
        below = activations[i]
        # δᵀ·h: [C, out, in], torch's weight layout, so no transpose is copied
        weights = np.matmul(delta.transpose(0, 2, 1), below)
        parts[:, offset : offset + n_in * n_out] = weights.reshape(num_chunks, -1)
        parts[:, offset + n_in * n_out : offset + n_in * n_out + n_out] = np.matmul(ones, delta)[
            :, 0, :
        ]
        if i > 0:
            delta = np.matmul(delta, per_chunk[i][0].transpose(0, 2, 1))
            below *= below
            np.subtract(1.0, below, out=below)
            delta *= below  # tanh' = 1 − h² at the layer below
