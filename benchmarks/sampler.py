"""Sampler throughput against a bare loop stepping the same vectorised env with random actions.

Both loops run in this process, one after the other, on one thread; the figure that matters is
the ratio. Usage: ``python -m benchmarks.sampler``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from fedhpg.common.policies import Policy, PolicyConfig, make_policy
from fedhpg.common.rollout import sample_trajectories
from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.registry import make_variants

REPEATS = 7


@dataclass(frozen=True)
class SamplerResult:
    name: str
    num_envs: int
    sampler_steps_per_s: float
    bare_steps_per_s: float

    @property
    def ratio(self) -> float:
        return self.sampler_steps_per_s / self.bare_steps_per_s


def _bare_loop(env: BatchEnv, horizon: int, seconds: float, rng: np.random.Generator) -> float:
    """Env steps/s of reset + random actions, counting only steps of running episodes."""
    space = env.single_action_space
    counted, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        env.reset(seed=int(rng.integers(2**31)))
        running = np.ones(env.num_envs, dtype=bool)
        for _ in range(horizon):
            actions = rng.integers(0, space.n, size=env.num_envs)  # type: ignore[attr-defined]
            step = env.step(actions)
            counted += int(running.sum())
            running &= ~(step.terminated | step.truncated)
            if not running.any():
                break
    return counted / (time.perf_counter() - started)


def _sampler_loop(
    env: BatchEnv, policy: Policy, horizon: int, seconds: float, rng: np.random.Generator
) -> float:
    counted, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        counted += sample_trajectories(env, policy, rng, horizon=horizon).num_steps
    return counted / (time.perf_counter() - started)


def measure(variant: EnvVariant, num_envs: int, *, seconds: float = 3.0) -> SamplerResult:
    env = variant.make_batch_env(num_envs)
    probe = variant.make_env()
    policy = make_policy(probe.observation_space, probe.action_space, PolicyConfig(hidden=[64, 64]))
    probe.close()
    horizon = variant.max_episode_steps
    rng = np.random.default_rng(0)
    _sampler_loop(env, policy, horizon, 0.3, rng)  # warm-up
    # Interleaved slices, so a change in machine load hits both loops alike.
    bare, ours = [], []
    for _ in range(REPEATS):
        bare.append(_bare_loop(env, horizon, seconds / REPEATS, rng))
        ours.append(_sampler_loop(env, policy, horizon, seconds / REPEATS, rng))
    env.close()
    return SamplerResult(variant.family, num_envs, float(np.median(ours)), float(np.median(bare)))


def run(seconds: float = 3.0) -> list[SamplerResult]:
    torch.set_num_threads(1)
    gridworld = make_variants("gridworld", seed=0, num_agents=1, level=0.5)[0]
    cartpole = make_variants("cartpole", seed=0, num_agents=1, level=0.0)[0]
    return [
        measure(gridworld, 64, seconds=seconds),
        measure(cartpole, 32, seconds=seconds),
    ]


def table(results: list[SamplerResult]) -> str:
    lines = [
        "| env | B | sampler (env steps/s) | bare random loop (env steps/s) | ratio |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {r.name} | {r.num_envs} | {r.sampler_steps_per_s:,.0f} | "
        f"{r.bare_steps_per_s:,.0f} | {r.ratio:.2f} |"
        for r in results
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    print(table(run()))
