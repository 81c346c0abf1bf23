"""The two references of ``make bench-scale``: env steps per second of a bare batched
gymnasium CartPole loop (the physical limit) and of the same loop plus one stacked forward
and action draw of every agent's own MLP per step (the unavoidable work)."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np

from benchmarks.results_file import cpu_description as cpu_description
from fedhpg.common.learning.batched.mlp import MLPShape


def bare_loop(num_envs: int, steps: int, seed: int = 0) -> float:
    """(a): env steps/s of ``gym.make_vec`` CartPole with random actions."""
    env = gym.make_vec("CartPole-v1", num_envs=num_envs, vectorization_mode="vector_entry_point")
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    actions = rng.integers(0, 2, size=(steps, num_envs))
    started = time.perf_counter()
    for t in range(steps):
        env.step(actions[t])
    elapsed = time.perf_counter() - started
    env.close()
    return num_envs * steps / elapsed


def forward_loop(copies: list[int], hidden: tuple[int, ...], steps: int, seed: int = 0) -> float:
    """(b): (a) plus, per step, each agent's own MLP on its copies (stacked per copy count)
    and one categorical draw per copy."""
    counts = np.asarray(sorted(copies))
    num_envs = int(counts.sum())
    env = gym.make_vec("CartPole-v1", num_envs=num_envs, vectorization_mode="vector_entry_point")
    rng = np.random.default_rng(seed)
    shape = MLPShape((4, *hidden, 2))
    params = (0.1 * rng.standard_normal((len(counts), shape.num_params))).astype(np.float32)
    groups = []
    start = 0
    for size in np.unique(counts):
        num = int((counts == size).sum())
        row = int(counts[:start].sum())
        groups.append((row, num, int(size), unflatten(shape, params[start : start + num])))
        start += num
    obs, _ = env.reset(seed=seed)
    started = time.perf_counter()
    for _ in range(steps):
        actions = np.empty(num_envs, dtype=np.int64)
        uniforms = rng.random(num_envs)
        for row, num, size, layers in groups:
            rows = slice(row, row + num * size)
            logit = logits(layers, obs[rows].reshape(num, size, -1)).reshape(num * size, -1)
            actions[rows] = draw_actions(logit, uniforms[rows])
        obs, *_ = env.step(actions)
    elapsed = time.perf_counter() - started
    env.close()
    return num_envs * steps / elapsed


# -- (b)'s own numpy forward: a fixed reference, independent of the engine ----------------

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
