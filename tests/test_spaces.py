"""Every gymnasium space a user meets: ids without a step limit need ``env.horizon``; Dict and
Tuple observations reach the policy flattened (a Discrete one-hot, as gymnasium flattens it);
MultiDiscrete and MultiBinary actions get a product of categoricals; images a small CNN. Each
is run through the engine on a real gymnasium id (``Blackjack-v1``, ``CliffWalking-v1``,
``CarRacing-v3``) or, for the spaces no shipped id has, ``spaces/Beacon-v0``
(tests/fedhpg_spaces_plugin.py)."""

from __future__ import annotations

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.policy import PolicyConfig
from fedhpg.common.heterogeneity.variants import variant_of
from fedhpg.common.learning.engine.policy_rows import PolicyRows
from fedhpg.common.learning.policies import (
    CNNPolicy,
    GaussianMLPPolicy,
    MLPCategoricalPolicy,
    MLPMultiCategoricalPolicy,
    get_flat_params,
    make_policy,
    set_flat_params,
)
from fedhpg.common.learning.worker import build_policy
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.spaces import is_flattened, is_image, policy_observation_space
from fedhpg.server.assembly import run_in_process

BLACKJACK = ["env=gym", "env.id=Blackjack-v1", "env.horizon=10"]
BEACON = ["plugins=[fedhpg_spaces_plugin]", "env=gym", "env.id=spaces/Beacon-v0"]
SHORT = ["rounds=1", "eval.episodes=1"]


def test_an_id_without_a_step_limit_needs_a_horizon() -> None:
    with pytest.raises(ConfigError, match="CliffWalking-v1 has no step limit") as error:
        compose(["env=gym", "env.id=CliffWalking-v1"])
    assert error.value.key == "env.horizon"
    run = compose(["env=gym", "env.id=CliffWalking-v1", "env.horizon=30", *SHORT])
    assert variant_of(run, 0).max_episode_steps == 30
    assert run_in_process(run).isfinite().all()


@pytest.mark.parametrize(
    ("overrides", "raw"),
    [
        (
            BLACKJACK,
            gym.spaces.Tuple(
                (gym.spaces.Discrete(32), gym.spaces.Discrete(11), gym.spaces.Discrete(2))
            ),
        ),
        (BEACON, None),
    ],
    ids=["tuple", "dict"],
)
def test_tuple_and_dict_observations_are_flattened_one_hot(
    overrides: list[str], raw: gym.Space | None
) -> None:
    variant = variant_of(compose(overrides), 1)
    env = variant.make_env()
    unwrapped = env.unwrapped.observation_space
    assert raw is None or unwrapped == raw
    assert is_flattened(unwrapped)
    assert env.observation_space == policy_observation_space(unwrapped)
    assert isinstance(env.observation_space, gym.spaces.Box)
    assert env.observation_space.shape == (gym.spaces.flatdim(unwrapped),)
    batch = variant.make_batch_env(3)
    try:
        assert batch.single_observation_space == env.observation_space
        first = batch.reset(seed=7)
        assert first.shape == (3, gym.spaces.flatdim(unwrapped))
        # copy i is seeded seed + i: the same first observation as one env seeded so
        for i in range(3):
            obs, _ = env.reset(seed=7 + i)
            np.testing.assert_array_equal(first[i], obs)
            assert set(np.unique(obs[: -1 if raw is None else None])) <= {0, 1}  # one-hot
        step = batch.step(np.zeros(3, dtype=np.int64))
        assert step.obs.shape == first.shape
    finally:
        batch.close()
        env.close()
    run = compose([*overrides, *SHORT])
    assert isinstance(build_policy(variant, run), MLPCategoricalPolicy)
    assert run_in_process(run).isfinite().all()


@pytest.mark.parametrize("action", ["multi_discrete", "multi_binary"])
def test_multi_actions_run_through_the_engine(action: str) -> None:
    run = compose([*BEACON, f"+env.kwargs.action={action}", *SHORT])
    policy = build_policy(variant_of(run, 0), run)
    assert isinstance(policy, MLPMultiCategoricalPolicy)
    assert policy.noise_size == 3  # three components either way (Beacon's width is 3)
    assert run_in_process(run).isfinite().all()


# --- the multi-categorical policy --------------------------------------------------------------


def _multi(nvec: list[int], start: list[int] | None = None) -> MLPMultiCategoricalPolicy:
    torch.manual_seed(0)
    policy = MLPMultiCategoricalPolicy(obs_dim=3, nvec=nvec, start=start, hidden=[8])
    with torch.no_grad():  # logits far from uniform, so a wrong component would show
        last = policy.net[-1]
        assert isinstance(last, torch.nn.Linear)
        last.weight.normal_(0.0, 2.0)
        last.bias.normal_(0.0, 1.0)
    return policy


def test_multi_categorical_log_prob_is_the_sum_of_torchs_categoricals() -> None:
    nvec, start = [3, 1, 5], [0, -2, 10]
    policy = _multi(nvec, start)
    obs = torch.randn(4, 6, 3)
    flat = policy.net(obs)
    pieces = torch.split(flat, nvec, dim=-1)
    act = torch.stack(
        [torch.randint(0, n, (4, 6)) + s for n, s in zip(nvec, start, strict=True)], -1
    )
    expected = sum(
        torch.distributions.Categorical(logits=piece).log_prob(act[..., i] - start[i])
        for i, piece in enumerate(pieces)
    )
    torch.testing.assert_close(policy.log_prob(obs, act), expected)
    # differentiable in θ, and the rows' call is the one policy's per row
    policy.log_prob(obs, act).sum().backward()
    assert all(p.grad is not None and p.grad.isfinite().all() for p in policy.parameters())


def test_multi_binary_log_prob_is_the_sum_of_torchs_bernoullis() -> None:
    policy = make_policy(
        gym.spaces.Box(-1, 1, (3,)), gym.spaces.MultiBinary(4), PolicyConfig(hidden=[8])
    )
    assert isinstance(policy, MLPMultiCategoricalPolicy)
    obs = torch.randn(7, 3)
    act = torch.randint(0, 2, (7, 4))
    pairs = policy.net(obs).unflatten(-1, (4, 2))
    bernoulli = torch.distributions.Bernoulli(logits=pairs[..., 1] - pairs[..., 0])
    torch.testing.assert_close(policy.log_prob(obs, act), bernoulli.log_prob(act.float()).sum(-1))


def test_multi_categorical_draws_follow_each_component() -> None:
    """Chi-square per component over n draws: (observed − n p)² / (n p) summed has mean
    (values − 1) and variance 2 (values − 1); six standard deviations above the mean is a
    false alarm about once in 10⁵ seeds, a wrong component's bias of 1 % gives ~n·10⁻⁴ ≫."""
    nvec, start = [3, 2, 5], [1, 0, -1]
    policy = _multi(nvec, start)
    obs = torch.randn(1, 3)
    n = 200_000
    noise = torch.from_numpy(np.random.default_rng(0).random((n, len(nvec)))).float()
    with torch.no_grad():
        actions = policy.act(obs.expand(n, 3), noise).numpy()
        logits = policy.net(obs)[0]
    for i, (values, first) in enumerate(zip(nvec, start, strict=True)):
        probs = torch.softmax(torch.split(logits, nvec)[i], -1).numpy()
        counts = np.bincount(actions[:, i] - first, minlength=values)
        assert counts.size == values, "no draw outside the component's values"
        chi2 = float(np.sum((counts - n * probs) ** 2 / (n * probs)))
        dof = values - 1
        assert chi2 < dof + 6 * np.sqrt(2 * dof), (i, chi2, probs)
    greedy = policy.act(obs, None)[0].numpy()
    expected = [int(p.argmax()) + s for p, s in zip(torch.split(logits, nvec), start, strict=True)]
    np.testing.assert_array_equal(greedy, expected)
    # the components' draws are independent: the joint of components 0 and 1 factorises
    joint = np.zeros((3, 2))
    np.add.at(joint, (actions[:, 0] - 1, actions[:, 1]), 1)
    independent = np.outer(joint.sum(1), joint.sum(0)) / n
    chi2 = float(np.sum((joint - independent) ** 2 / independent))
    assert chi2 < 2 + 6 * np.sqrt(4)


def test_auto_picks_a_policy_for_every_action_space() -> None:
    config = PolicyConfig(hidden=[8])
    box = gym.spaces.Box(-1, 1, (3,))
    image = gym.spaces.Box(0, 255, (24, 24, 3), dtype=np.uint8)
    assert is_image(image) and not is_image(box)
    assert isinstance(
        make_policy(box, gym.spaces.MultiDiscrete([2, 3]), config), MLPMultiCategoricalPolicy
    )
    assert isinstance(
        make_policy(box, gym.spaces.MultiBinary(2), config), MLPMultiCategoricalPolicy
    )
    discrete_head = make_policy(image, gym.spaces.Discrete(5), config)
    assert isinstance(discrete_head, CNNPolicy)
    assert isinstance(discrete_head.head, MLPCategoricalPolicy)
    gaussian_head = make_policy(image, gym.spaces.Box(-1, 1, (3,)), config)
    assert isinstance(gaussian_head, CNNPolicy) and isinstance(
        gaussian_head.head, GaussianMLPPolicy
    )
    with pytest.raises(ConfigError, match="policy 'cnn' needs image observations"):
        make_policy(box, gym.spaces.Discrete(2), PolicyConfig(name="cnn"))
    with pytest.raises(ValueError, match="Discrete observations take Discrete actions"):
        make_policy(gym.spaces.Discrete(4), gym.spaces.Box(-1, 1, (2,)), config)
    with pytest.raises(ValueError, match="unsupported action space"):
        make_policy(box, gym.spaces.MultiDiscrete(np.full((2, 2), 2)), config)


# --- the CNN policy ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "shape", [(96, 96, 3), (1, 40, 40)], ids=["channels-last", "channels-first"]
)
@pytest.mark.parametrize("action", ["discrete", "box"])
def test_cnn_keeps_the_policy_contract(shape: tuple[int, ...], action: str) -> None:
    image = gym.spaces.Box(0, 255, shape, dtype=np.uint8)
    actions = gym.spaces.Discrete(5) if action == "discrete" else gym.spaces.Box(-1, 1, (3,))
    torch.manual_seed(3)
    policy = make_policy(image, actions, PolicyConfig(hidden=[16]))
    assert isinstance(policy, CNNPolicy) and not policy.rows_batched
    theta = get_flat_params(policy)
    assert theta.dtype == torch.float32 and theta.numel() < 60_000
    generator = torch.Generator().manual_seed(0)
    obs = torch.randint(0, 256, (2, 4, *shape), dtype=torch.uint8, generator=generator)
    noise = torch.rand(2, 4, policy.noise_size, generator=generator)
    act = policy.act(obs, noise).detach()
    torch.testing.assert_close(policy.act(obs, noise).detach(), act)  # every draw from the noise
    log_prob = policy.log_prob(obs, act)
    assert log_prob.shape == (2, 4) and log_prob.isfinite().all()
    log_prob.sum().backward()
    assert all(p.grad is not None for p in policy.parameters())
    first = policy.conv[0]
    assert isinstance(first, torch.nn.Conv2d) and first.weight.grad is not None
    assert first.weight.grad.abs().sum() > 0
    # rows of θ through the engine's per-row calls (vmapped): row a is the policy under θ_a
    rows = PolicyRows(policy, torch.device("cpu"))
    thetas = torch.stack([theta, theta + 0.01 * torch.randn(theta.shape, generator=generator)])
    per_row = rows.log_probs(thetas, obs, act)
    torch.testing.assert_close(per_row[0], log_prob.detach()[0])
    other = copy.deepcopy(policy)
    set_flat_params(other, thetas[1])
    with torch.no_grad():
        torch.testing.assert_close(per_row[1], other.log_prob(obs[1], act[1]))
        torch.testing.assert_close(rows.act(thetas, obs, noise)[1], other.act(obs[1], noise[1]))
    gradients = rows.score_gradients(thetas, obs, act, torch.ones(2, 4))
    assert gradients.shape == (2, theta.numel()) and gradients.isfinite().all()


def test_car_racing_runs_through_the_engine_with_a_cnn() -> None:
    run = compose(
        ["env=gym", "env.id=CarRacing-v3", "env.horizon=10", "agents.budget.batch_size=[1]", *SHORT]
    )
    variant = variant_of(run, 0)
    assert is_image(variant.make_env().observation_space)
    policy = build_policy(variant, run)
    assert isinstance(policy, CNNPolicy) and isinstance(policy.head, GaussianMLPPolicy)
    assert run_in_process(run).isfinite().all()
