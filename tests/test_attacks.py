"""Byzantine agents by configuration: never by default, only the listed agents, FedPG-BR's
magnitudes, and every attack reproducible from the agent's random streams."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch

from fedhpg.common.configuration.settings.attack import AttackConfig
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.attacks import corrupt_rows
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.engine.sampling import _random_actions
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord

START = torch.zeros(50)
HONEST = torch.linspace(-1.0, 2.0, 50)


def test_no_agent_attacks_by_default() -> None:
    attack = compose([]).attack
    assert attack.kind == "none" and attack.agents == []


def _sent(kind: str, start: torch.Tensor, honest: torch.Tensor) -> torch.Tensor:
    attack = AttackConfig(kind=kind, agents=[3])
    rows = corrupt_rows(attack, start, honest.unsqueeze(0), [3], seed=0, round_index=1)
    return rows[0]


def test_update_attacks_have_fedpg_brs_magnitudes() -> None:
    assert torch.equal(_sent("zero_gradient", START + 1, HONEST + 1), START + 1)
    torch.testing.assert_close(_sent("sign_flip", START, HONEST), -2.5 * HONEST)
    noisy = _sent("random_noise", START, HONEST) - HONEST
    spread = float(HONEST.max() - HONEST.min())
    assert float(noisy.abs().max()) <= 3.0 * spread  # U(−1, 1) · 3 · (max − min)
    assert float(noisy.abs().max()) > 0.5 * 3.0 * spread, "and it is that large, not tiny"
    honest_agent = corrupt_rows(AttackConfig(kind="sign_flip", agents=[3]), START,
                                HONEST.unsqueeze(0), [2], seed=0, round_index=1)  # fmt: skip
    assert torch.equal(honest_agent[0], HONEST), "only the listed agents attack"


def _engine(overrides: list[str]) -> Engine:
    run = compose([
        "env=cartpole", "algo.engine=torch", "policy.hidden=[8]", "agents.num_agents=2",
        "agents.budget.batch_size=[4]", "agents.budget.local_iters=[1]", "agents.speeds=[1]",
        "agents.step_delays_s=[0]", *overrides,
    ])  # fmt: skip
    return Engine(run, variants_of(run, [0, 1]))


def test_reward_flip_negates_only_the_attackers_rewards() -> None:
    honest, flipped = (
        _engine(extra) for extra in ([], ["attack=reward_flip", "attack.agents=[1]"])
    )
    batches = []
    for engine in (honest, flipped):
        rows = engine.begin(1, initial_theta(engine.variants[0], engine.run), [0, 1])
        batches.append(rows.sample(rows.theta, torch.tensor([3, 3]), iteration=0))
    clean, attacked = batches
    torch.testing.assert_close(attacked.rewards[:, 3:], -clean.rewards[:, 3:])
    assert torch.equal(attacked.rewards[:, :3], clean.rewards[:, :3])
    assert torch.equal(attacked.obs, clean.obs) and torch.equal(attacked.actions, clean.actions)


def test_random_actions_are_uniform_and_scored_by_the_policy() -> None:
    """An attacker whose policy almost always picks action 1 acts uniformly instead; its
    gradient is computed for those actions under its policy's log-probabilities."""
    engine = _engine(["attack=random_action", "attack.agents=[0]"])
    theta = initial_theta(engine.variants[0], engine.run)
    rows = engine.begin(1, theta, [0, 1])
    skewed = rows.theta.clone()
    skewed[:, -2:] = torch.tensor([-9.0, 9.0])  # the last layer's biases
    batch = rows.sample(skewed, torch.tensor([400, 400]), iteration=0)
    actions = batch.actions[batch.alive]
    owner = batch.owner.expand_as(batch.alive)[batch.alive]
    attacker = actions[owner == 0].double()
    honest = actions[owner == 1].double()
    share = float(attacker.mean())
    assert abs(share - 0.5) < 5 * (0.25 / len(attacker)) ** 0.5, share
    assert float(honest.mean()) > 0.99, "the honest agent follows its policy"
    log_probs = rows.log_probs(skewed, batch)[batch.alive]
    assert float(log_probs[owner == 0][attacker == 0].max()) < -15, "scored by the policy"
    box = _random_actions(
        torch.zeros(1000, 2), torch.ones(1000, dtype=torch.bool), torch.arange(1000), 0, 2,
        gym.spaces.Box(-2.0, 1.0, (2,)),
    )  # fmt: skip
    assert box.shape == (1000, 2) and float(box.min()) >= -2.0 and float(box.max()) <= 1.0


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
        return list(torch.from_numpy(records[0].result.thetas.copy()))

    honest = thetas(keys)
    attacked = thetas([*keys, f"attack.kind={kind}", "attack.agents=[1]"])
    assert torch.equal(attacked[0], honest[0]) and torch.equal(attacked[2], honest[2])
    assert not torch.equal(attacked[1], honest[1])
    assert torch.equal(thetas([*keys, f"attack.kind={kind}", "attack.agents=[1]"])[1], attacked[1])
