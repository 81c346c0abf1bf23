"""The two references of ``make bench-scale``: env steps per second of a bare batched
gymnasium CartPole loop (the physical limit) and of the same loop plus one stacked forward
and action draw of every agent's own MLP per step (the unavoidable work)."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np

from fedhpg.common.batched import mlp


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
    shape = mlp.MLPShape((4, *hidden, 2))
    params = (0.1 * rng.standard_normal((len(counts), shape.num_params))).astype(np.float32)
    groups = []
    start = 0
    for size in np.unique(counts):
        num = int((counts == size).sum())
        row = int(counts[:start].sum())
        groups.append((row, num, int(size), mlp.unflatten(shape, params[start : start + num])))
        start += num
    obs, _ = env.reset(seed=seed)
    started = time.perf_counter()
    for _ in range(steps):
        actions = np.empty(num_envs, dtype=np.int64)
        uniforms = rng.random(num_envs)
        for row, num, size, layers in groups:
            rows = slice(row, row + num * size)
            logit = mlp.logits(layers, obs[rows].reshape(num, size, -1)).reshape(num * size, -1)
            actions[rows] = mlp.draw_actions(logit, uniforms[rows])
        obs, *_ = env.step(actions)
    elapsed = time.perf_counter() - started
    env.close()
    return num_envs * steps / elapsed
