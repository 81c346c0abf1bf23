"""Byzantine agents by configuration: never by default, only the listed agents, FedPG-BR's
magnitudes, and every attack reproducible from the agent's random streams."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from fedhpg.common.attacks import corrupt_batch, corrupt_update, random_action_sampler
from fedhpg.common.config import AttackConfig
from fedhpg.common.policies import MLPCategoricalPolicy
from fedhpg.common.rollout import TrajectoryBatch
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord

START = torch.zeros(50)
HONEST = torch.linspace(-1.0, 2.0, 50)


def test_no_agent_attacks_by_default() -> None:
    attack = compose([]).attack
    assert attack.kind == "none" and attack.agents == []


def test_update_attacks_have_fedpg_brs_magnitudes() -> None:
    attack = AttackConfig(kind="sign_flip", agents=[0])
    rng = np.random.default_rng(0)
    assert torch.equal(
        corrupt_update("zero_gradient", START + 1, HONEST + 1, attack, rng), START + 1
    )
    torch.testing.assert_close(
        corrupt_update("sign_flip", START, HONEST, attack, rng), -2.5 * HONEST
    )
    noisy = corrupt_update("random_noise", START, HONEST, attack, rng) - HONEST
    spread = float(HONEST.max() - HONEST.min())
    assert float(noisy.abs().max()) <= 3.0 * spread  # U(−1, 1) · 3 · (max − min)
    assert float(noisy.abs().max()) > 0.5 * 3.0 * spread, "and it is that large, not tiny"


def test_reward_flip_negates_only_the_rewards() -> None:
    batch = TrajectoryBatch(
        obs=np.zeros((3, 2, 4), np.float32),
        actions=np.zeros((3, 2), np.int64),
        log_probs=np.zeros((3, 2)),
        rewards=np.arange(6.0).reshape(3, 2),
        alive=np.ones((3, 2), bool),
        success=np.zeros(2, bool),
    )
    flipped = corrupt_batch("reward_flip", batch)
    assert np.array_equal(flipped.rewards, -batch.rewards)
    assert flipped.obs is batch.obs and corrupt_batch("sign_flip", batch) is batch


def test_random_actions_are_uniform_and_scored_by_the_policy() -> None:
    policy = MLPCategoricalPolicy(obs_dim=4, num_actions=3, hidden=[8])
    with torch.no_grad():  # a policy that almost always picks action 2
        policy.net[-1].bias.copy_(torch.tensor([-9.0, -9.0, 9.0]))
    sampler = random_action_sampler(gym.spaces.Discrete(3), policy.sampler())
    obs = np.zeros((30_000, 4), np.float32)
    actions = sampler(obs, np.random.default_rng(1), False)
    counts = np.bincount(actions, minlength=3) / len(actions)
    # Uniform: each count within 5 standard errors (√(p(1−p)/n) ≈ 0.0027) of 1/3.
    assert np.all(np.abs(counts - 1 / 3) < 5 * np.sqrt(2 / 9 / len(actions))), counts
    np.testing.assert_allclose(
        sampler.log_prob(obs[:3], actions[:3]), policy.sampler().log_prob(obs[:3], actions[:3])
    )
    box = random_action_sampler(gym.spaces.Box(-2.0, 1.0, (2,)), policy.sampler())
    drawn = box(obs[:1000], np.random.default_rng(2), False)
    assert drawn.shape == (1000, 2) and drawn.min() >= -2.0 and drawn.max() <= 1.0


@pytest.mark.parametrize(
    "kind", ["zero_gradient", "random_noise", "sign_flip", "reward_flip", "random_action"]
)
def test_only_the_listed_agents_attack_and_attacks_are_reproducible(kind: str) -> None:
    keys = [
        "rounds=1", "env.family=cartpole", "agents.num_agents=3", "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
        "algo.step_size=0.01", "eval.every=1", "eval.episodes=2",
    ]  # fmt: skip

    def thetas(overrides: list[str]) -> list[torch.Tensor]:
        records: list[RoundRecord] = []
        run_in_process(compose(overrides), on_round=[lambda r, _: records.append(r)])
        return [a.theta for a in records[0].agents]

    honest = thetas(keys)
    attacked = thetas([*keys, f"attack.kind={kind}", "attack.agents=[1]"])
    assert torch.equal(attacked[0], honest[0]) and torch.equal(attacked[2], honest[2])
    assert not torch.equal(attacked[1], honest[1])
    assert torch.equal(thetas([*keys, f"attack.kind={kind}", "attack.agents=[1]"])[1], attacked[1])
