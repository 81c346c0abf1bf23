"""Sampler throughput against bare loops with random actions, in this process, on one thread.

GridWorld and CartPole: the sampler against a bare loop stepping the *same* batched env.
LunarLander and HalfCheetah: the sampler (on :class:`GymLoopBatchEnv`, and on gymnasium's
``SyncVectorEnv`` as before it) against a bare gymnasium loop: one ``gym.make`` env, random
actions, reset when an episode ends. The loops run interleaved; the figure that matters is the
ratio. Usage: ``python -m benchmarks.sampler``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from benchmarks import results_file
from fedhpg.common.learning.engine.copies import GymBlocks
from fedhpg.common.learning.engine.policy_rows import PolicyRows
from fedhpg.common.learning.engine.sampling import sample
from fedhpg.common.learning.policies import Policy, PolicyConfig, get_flat_params, make_policy
from fedhpg.common.learning.randomness import Purpose, trajectory_keys
from fedhpg.envs.base import BatchEnv, EnvVariant
from fedhpg.envs.gym_adapter import GymVectorBatchEnv
from fedhpg.envs.gym_variant import GymVariant
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
    """The engine's sampler (one agent's row, ``env.num_envs`` trajectories a batch) on
    ``env``: env steps/s of the trajectories' alive steps."""
    cpu = torch.device("cpu")
    rows = PolicyRows(policy, cpu)
    theta = get_flat_params(policy).unsqueeze(0)
    copies = GymBlocks([env], cpu)
    count = env.num_envs
    counts, horizons = torch.tensor([count]), torch.tensor([horizon])
    counted, started, batch_number = 0, time.perf_counter(), int(rng.integers(2**31))
    while time.perf_counter() - started < seconds:
        keys = trajectory_keys(0, torch.zeros(count, dtype=torch.int64), batch_number,
                               Purpose.TRAIN, 0, torch.arange(count))  # fmt: skip
        counted += int(sample(rows, copies, theta, counts, keys, horizons).alive.sum())
        batch_number += 1
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


@dataclass(frozen=True)
class GymResult:
    name: str
    num_envs: int
    sampler_steps_per_s: float
    """Our sampler on the variant's batch env (:class:`GymLoopBatchEnv`)."""
    sync_sampler_steps_per_s: float
    """Our sampler on gymnasium's ``SyncVectorEnv`` (the batch env before GymLoopBatchEnv)."""
    bare_steps_per_s: float
    """One plain ``gym.make`` env, random actions, reset at episode end."""

    @property
    def ratio(self) -> float:
        return self.sampler_steps_per_s / self.bare_steps_per_s

    @property
    def sync_ratio(self) -> float:
        return self.sync_sampler_steps_per_s / self.bare_steps_per_s


def _bare_gym_loop(env: gym.Env, seconds: float, rng: np.random.Generator) -> float:
    """Steps/s of the plainest gymnasium loop: step with a random action, reset when done."""
    space = env.action_space
    discrete = isinstance(space, gym.spaces.Discrete)
    counted, started = 0, time.perf_counter()
    env.reset(seed=int(rng.integers(2**31)))
    while time.perf_counter() - started < seconds:
        for _ in range(100):  # check the clock every 100 steps, not every step
            if discrete:
                action = rng.integers(0, space.n)  # type: ignore[attr-defined]
            else:
                action = rng.uniform(space.low, space.high).astype(np.float32)  # type: ignore[attr-defined]
            _, _, terminated, truncated, _ = env.step(action)
            counted += 1
            if terminated or truncated:
                env.reset(seed=int(rng.integers(2**31)))
    return counted / (time.perf_counter() - started)


def measure_gym(variant: GymVariant, num_envs: int, *, seconds: float = 6.0) -> GymResult:
    """Our sampler (new and old batch env) against a bare gymnasium loop, interleaved."""
    loop_env = variant.make_batch_env(num_envs)
    sync_env = GymVectorBatchEnv(
        variant.env_id,
        num_envs,
        env_kwargs=variant.env_kwargs,
        configure=variant.configure,
        action_cost=variant.action_cost,
    )
    single = variant.make_env()
    policy = make_policy(
        single.observation_space, single.action_space, PolicyConfig(hidden=[64, 64])
    )
    horizon = variant.max_episode_steps
    rng = np.random.default_rng(0)
    _sampler_loop(loop_env, policy, horizon, 0.3, rng)  # warm-up
    ours, sync, bare = [], [], []
    for _ in range(REPEATS):
        bare.append(_bare_gym_loop(single, seconds / REPEATS, rng))
        ours.append(_sampler_loop(loop_env, policy, horizon, seconds / REPEATS, rng))
        sync.append(_sampler_loop(sync_env, policy, horizon, seconds / REPEATS, rng))
    for env in (loop_env, sync_env, single):
        env.close()
    return GymResult(
        variant.env_id,
        num_envs,
        float(np.median(ours)),
        float(np.median(sync)),
        float(np.median(bare)),
    )


def run(seconds: float = 3.0) -> list[SamplerResult]:
    torch.set_num_threads(1)
    gridworld = make_variants("gridworld", seed=0, num_agents=1, level=0.5)[0]
    cartpole = make_variants("cartpole", seed=0, num_agents=1, level=0.0)[0]
    return [
        measure(gridworld, 64, seconds=seconds),
        measure(cartpole, 32, seconds=seconds),
    ]


def run_gym(seconds: float = 6.0) -> list[GymResult]:
    """LunarLander (B=32, FedPG-BR's batch) and HalfCheetah (B=16: one batch of 1000-step
    episodes already takes ~0.5 s) at level 0."""
    torch.set_num_threads(1)
    results = []
    for family, num_envs in (("lunarlander", 32), ("halfcheetah", 16)):
        variant = make_variants(family, seed=0, num_agents=1, level=0.0)[0]
        assert isinstance(variant, GymVariant)
        results.append(measure_gym(variant, num_envs, seconds=seconds))
    return results


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


def gym_table(results: list[GymResult]) -> str:
    lines = [
        "| env | B | sampler, GymLoopBatchEnv (steps/s) | sampler, SyncVectorEnv (steps/s) "
        "| bare gymnasium loop (steps/s) | ratio | ratio with SyncVectorEnv |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r.name} | {r.num_envs} | {r.sampler_steps_per_s:,.0f} | "
        f"{r.sync_sampler_steps_per_s:,.0f} | {r.bare_steps_per_s:,.0f} | {r.ratio:.2f} | "
        f"{r.sync_ratio:.2f} |"
        for r in results
    ]
    return "\n".join(lines)


def main() -> None:
    batched, gym_loops = run(), run_gym()
    print(table(batched))
    print()
    print(gym_table(gym_loops))
    ratios = [r.ratio for r in batched] + [r.ratio for r in gym_loops]
    results_file.write(
        "sampler",
        title="Sampler throughput",
        order=200,
        command="python -m benchmarks.sampler",
        measures=["common/learning/engine", "common/learning/batched", "envs"],
        setup=(
            "The rollout sampler against a bare loop with random actions, interleaved in "
            f"{REPEATS} slices, medians, on one thread; only steps of running episodes count. "
            "GridWorld and CartPole: the bare loop steps the same batched environment. "
            "LunarLander and HalfCheetah: the sampler on `GymLoopBatchEnv` (and on gymnasium's "
            "SyncVectorEnv) against one `gym.make` environment stepped and reset in a loop."
        ),
        tables=[
            results_file.table_from_markdown(
                table(batched),
                "The sampler against a bare loop stepping the same batched environment.",
            ),
            results_file.table_from_markdown(
                gym_table(gym_loops),
                f"Over all four, the sampler runs at {min(ratios):.2f}–{max(ratios):.2f} × a "
                "bare random loop over the same environment.",
            ),
        ],
    )


if __name__ == "__main__":
    main()
