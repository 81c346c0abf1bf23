"""The torch families against gymnasium's own environments, step for step.

For variants drawn by the families at level 1 (every constant changed), each copy is put in a
random state (angles past ±π, speeds at and past their bounds, a car at the wall), both take the
same action, and the next observation, reward and termination agree (to float32 rounding:
gymnasium steps in float64). GridWorld's moves are checked for every variant, cell and action,
with and without a slip, against ``GridWorldEnv`` fed the same decision; its slips' frequencies
against the exact transition table. Truncation comes at each variant's step limit, and a copy's
reset is a function of its own stream alone. Through the engine, the two environment paths
(``algo.envs``) give returns of the same distribution.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.randomness import Purpose, trajectory_keys, uniforms64
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose
from fedhpg.envs.device import device_copies, device_family
from fedhpg.envs.device.cartpole import CartPoleCopies
from fedhpg.envs.device.tensors import TensorCopies
from fedhpg.envs.gridworld import GridWorldEnv, GridWorldVariant

CPU = torch.device("cpu")
COPIES = 20


class _Stream:
    def __init__(self, uniforms: torch.Tensor) -> None:
        self.values = uniforms

    def uniforms(self, count: int) -> torch.Tensor:
        return self.values[:, :count]

    def seeds(self) -> list[int]:
        return [0] * len(self.values)


def _variants(env: str, count: int, *overrides: str) -> list:
    run = compose([f"env={env}", "env.level=1.0", "agents=population",
                   f"agents.num_agents={count}", *overrides])  # fmt: skip
    variants = variants_of(run, list(range(count)))
    return [variants[k] for k in range(count)]


# (family, state low, state high, discrete actions or None for a torque in [−3, 3])
CLASSIC = {
    "cartpole": ([-2.3, -2.0, -0.2, -2.5], [2.3, 2.0, 0.2, 2.5], 2),
    "acrobot": ([-math.pi, -math.pi, -14.0, -30.0], [math.pi, math.pi, 14.0, 30.0], 3),
    "pendulum": ([-3 * math.pi, -8.5], [3 * math.pi, 8.5], None),
    "mountaincar": ([-1.2, -0.07], [0.6, 0.07], 3),
}
TOLERANCE = {"cartpole": 1e-6, "acrobot": 1e-4, "pendulum": 1e-5, "mountaincar": 1e-6}
"""Absolute tolerance of the observations (with rtol 1e-5): float32 against float64 rounding;
Acrobot's RK4 compounds four evaluations on speeds up to 9π."""


def _states(name: str, count: int, rng: np.random.Generator) -> np.ndarray:
    low, high, _ = CLASSIC[name]
    states = rng.uniform(low, high, size=(count, len(low)))
    if name == "mountaincar":  # some at the left wall, moving left: stopped there
        states[: count // 8] = [-1.19, -0.05]
    return states


@pytest.mark.parametrize("name", sorted(CLASSIC))
def test_each_family_steps_like_gymnasiums_for_every_variant(name: str) -> None:
    variants = _variants(name, 12)
    copies = device_copies(variants, [COPIES] * 12, CPU)
    assert isinstance(copies, TensorCopies)
    rng = np.random.default_rng(0)
    states = _states(name, copies.num_copies, rng)
    discrete = CLASSIC[name][2]
    actions = (
        rng.integers(0, discrete, size=copies.num_copies)
        if discrete
        else rng.uniform(-3.0, 3.0, size=(copies.num_copies, 1)).astype(np.float32)
    )
    copies.state[:] = torch.from_numpy(states.T).float()
    copies.steps[:] = 0
    step = copies.step(torch.from_numpy(actions), torch.arange(copies.num_copies), None)
    ended = 0
    for n in range(copies.num_copies):
        env = variants[n // COPIES].make_env()  # the gymnasium path's env, wrappers included
        env.reset(seed=0)
        env.unwrapped.state = states[n].astype(np.float32).astype(np.float64)  # the copy's own
        action = int(actions[n]) if discrete else actions[n]
        obs, reward, terminated, truncated, _ = env.step(action)
        np.testing.assert_allclose(step.obs[n].numpy(), obs, rtol=1e-5, atol=TOLERANCE[name])
        assert float(step.reward[n]) == pytest.approx(reward, rel=1e-5, abs=1e-5)
        assert bool(step.terminated[n]) == terminated, n
        assert not bool(step.truncated[n]) and not truncated
        ended += terminated
    # the sampled states reach both outcomes where the family has terminal states
    assert ended < copies.num_copies and (ended > 0 or name == "pendulum")


@pytest.mark.parametrize("name", sorted(CLASSIC))
def test_truncation_at_the_step_limit_and_a_reset_from_its_own_stream(name: str) -> None:
    variants = _variants(name, 2)
    copies = device_copies(variants, [3, 3], CPU)
    assert isinstance(copies, TensorCopies)
    columns = torch.arange(6)
    uniforms = torch.rand(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    first = copies.reset(columns, _Stream(uniforms))
    again = copies.reset(columns[3:], _Stream(uniforms[3:]))
    assert torch.equal(again, first[3:]), "a copy's start depends on its own draws alone"
    env = variants[0].make_env()
    assert first.shape == (6, *env.observation_space.shape)
    assert all(env.observation_space.contains(o.numpy()) for o in first)
    limit = variants[0].max_episode_steps
    copies.steps[:] = limit - 1
    actions = torch.zeros(6, 1) if CLASSIC[name][2] is None else torch.ones(6, dtype=torch.int64)
    step = copies.step(actions, columns, None)
    assert bool(step.truncated.all())


def test_acrobot_wraps_angles_of_any_magnitude() -> None:
    """Both angles land in [−π, π] after any step, even from states whose speeds carry them
    dozens of turns (the velocities are bounded only after the step); angles within three
    turns wrap as gymnasium's loop of subtractions does, bit for bit."""
    from fedhpg.envs.device.acrobot import _wrap

    count = 20_000
    copies = device_copies(_variants("acrobot", 2), [count // 2] * 2, CPU)
    assert isinstance(copies, TensorCopies)
    rng = np.random.default_rng(3)
    states = rng.uniform([-math.pi, -math.pi, -2e3, -2e3], [math.pi, math.pi, 2e3, 2e3],
                         size=(count, 4))  # fmt: skip
    copies.state[:] = torch.from_numpy(states.T).float()
    copies.steps[:] = 0
    actions = torch.from_numpy(rng.integers(0, 3, size=count))
    copies.step(actions, torch.arange(count), None)
    angles = copies.state[:2]
    assert bool(((angles >= -math.pi) & (angles <= math.pi)).all())

    extreme = torch.tensor([1e3, -1e3, 12345.678, -7e6, 3e7, 5 * math.pi, -9.5 * math.pi])
    wrapped = _wrap(extreme)
    assert bool(((wrapped >= -math.pi) & (wrapped <= math.pi)).all())
    turns = (extreme.double() - wrapped.double()) / (2 * math.pi)
    ulp = torch.finfo(torch.float32).eps * extreme.double().abs()
    assert bool(((turns - turns.round()).abs() * 2 * math.pi <= 4 * ulp + 1e-6).all())

    near = torch.from_numpy(rng.uniform(-7 * math.pi, 7 * math.pi, size=1000)).float()
    looped = near.clone()
    for _ in range(3):  # gymnasium's wrap: whole turns subtracted one at a time
        looped = torch.where(looped > math.pi, looped - 2 * math.pi, looped)
        looped = torch.where(looped < -math.pi, looped + 2 * math.pi, looped)
    assert torch.equal(_wrap(near), looped)


def test_cartpole_starts_in_gymnasiums_interval() -> None:
    copies = device_copies(_variants("cartpole", 2), [3, 3], CPU)
    assert isinstance(copies, CartPoleCopies)
    uniforms = torch.rand(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    first = copies.reset(torch.arange(6), _Stream(uniforms))
    torch.testing.assert_close(first, (uniforms * 0.1 - 0.05).float())


class _Decision:
    """GridWorldEnv's ``np_random`` fixed to one decision: ``random()`` then ``integers(3)``."""

    def __init__(self, u: float, j: int) -> None:
        self.u, self.j = u, j

    def random(self) -> float:
        return self.u

    def integers(self, n: int) -> int:
        assert n == 3
        return self.j


def _gridworlds(count: int) -> list[GridWorldVariant]:
    variants = _variants("gridworld", count)
    assert all(isinstance(v, GridWorldVariant) for v in variants)
    assert len({v.layout for v in variants}) > 1 and all(v.slip > 0 for v in variants)
    return variants


def test_gridworld_moves_like_gymnasiums_for_every_variant_cell_action_and_slip() -> None:
    """Decision j of 4 (3: no slip; j < 3: a slip to direction (a + 1 + j) mod 4): the copy
    takes u = (j + ½)·slip/3 (or u near 1), GridWorldEnv draws random() < slip and j."""
    variants = _gridworlds(6)
    cells = len(variants[0].layout) * len(variants[0].layout[0])
    grid = [(v, s, a, j) for v in range(6) for s in range(cells) for a in range(4)
            for j in range(4)]  # fmt: skip
    copies = device_copies(variants, [cells * 16] * 6, CPU)
    assert copies is not None and copies.step_noise == 1
    slip = torch.tensor([variants[v].slip for v, *_ in grid], dtype=torch.float64)
    j = torch.tensor([d for *_, d in grid], dtype=torch.float64)
    u = torch.where(j < 3, (j + 0.5) * slip / 3, 0.999)
    copies.state[0] = torch.tensor([s for _, s, _, _ in grid])
    copies.steps[:] = 0
    actions = torch.tensor([a for _, _, a, _ in grid])
    step = copies.step(actions, None, u.unsqueeze(1))
    for n, (v, s, a, d) in enumerate(grid):
        env = GridWorldEnv(layout=variants[v].layout, slip=variants[v].slip, max_steps=50)
        env.reset(seed=0)
        env._state = s
        env.np_random = _Decision(0.0 if d < 3 else 0.999, d)  # type: ignore[assignment]
        if env.model.terminal[s]:
            continue  # no step starts in an ended episode
        obs, reward, terminated, truncated, info = env.step(a)
        assert int(step.obs[n]) == int(obs), (v, s, a, d)
        assert float(step.reward[n]) == reward
        assert bool(step.terminated[n]) == terminated
        assert bool(step.success[n]) == info["is_success"]
        assert not bool(step.truncated[n]) and not truncated


def test_gridworld_slips_as_often_as_the_exact_transition_table_says() -> None:
    """20,000 steps from one cell and action per variant, each with its own counter-based
    uniform: the frequencies of the next cells against P[s, a, ·] (chi-square)."""
    variants = _gridworlds(3)
    draws = 20_000
    copies = device_copies(variants, [draws] * 3, CPU)
    assert copies is not None
    keys = trajectory_keys(0, torch.arange(3 * draws) // draws, 1, Purpose.TRAIN, 0,
                           torch.arange(3 * draws) % draws)  # fmt: skip
    noise = uniforms64(keys.unsqueeze(1), torch.tensor([[-(1 << 40)]]))
    start, action = 0, 3  # the start cell, moving right
    copies.state[0] = start
    step = copies.step(torch.full((3 * draws,), action), None, noise)
    for v, variant in enumerate(variants):
        exact = GridWorldEnv(layout=variant.layout, slip=variant.slip).transition_probs()
        expected = exact[start, action] * draws
        observed = torch.bincount(step.obs[v * draws : (v + 1) * draws], minlength=len(expected))
        seen = expected > 0
        assert int(observed[~torch.from_numpy(seen)].sum()) == 0
        statistic = float(((observed.numpy()[seen] - expected[seen]) ** 2 / expected[seen]).sum())
        dof = torch.tensor((int(seen.sum()) - 1) / 2)
        p_value = float(torch.special.gammaincc(dof, torch.tensor(statistic / 2)))
        assert p_value > 1e-4, (v, observed.tolist(), expected.tolist())


def test_gridworld_truncates_unless_terminated_and_resets_to_the_start() -> None:
    variants = _gridworlds(2)
    copies = device_copies(variants, [2, 2], CPU)
    assert copies is not None
    first = copies.reset(torch.arange(4), _Stream(torch.zeros(4, 0, dtype=torch.float64)))
    assert first.tolist() == [0, 0, 0, 0]
    copies.steps[:] = variants[0].max_steps - 1
    step = copies.step(torch.tensor([0, 0, 0, 0]), None, torch.full((4, 1), 0.999))
    assert step.obs.tolist() == [0, 0, 0, 0]  # up from the top-left corner: stays
    assert bool(step.truncated.all()) and not bool(step.terminated.any())


def test_gridworlds_draws_at_step_t_are_its_keys_counters_below_env_counters(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The uniform a copy's step t takes is hash(its trajectory key, ENV_COUNTERS − t): the
    sampler draws them a chunk of steps at a time, and what each step receives is that one
    draw, across the chunks' boundary and after the batch narrows to the copies that still
    run (a trajectory's slips depend on its key alone)."""
    from fedhpg.common.learning.engine import copies as copies_module
    from fedhpg.common.learning.engine.sampling import ENV_CHUNK, ENV_COUNTERS

    keys: list[torch.Tensor] = []
    draws: list[torch.Tensor] = []
    stepped: list[torch.Tensor] = []  # each step's copies, as the batch's columns
    blocks = copies_module.DeviceBlocks
    reset, step, keep = blocks.reset, blocks.step, blocks.keep

    def spy_reset(self, given):  # type: ignore[no-untyped-def]
        keys.append(given.clone())
        self.columns = torch.arange(len(given))
        return reset(self, given)

    def spy_step(self, actions, running, noise=None):  # type: ignore[no-untyped-def]
        draws.append(noise.clone())
        stepped.append(self.columns)
        return step(self, actions, running, noise)

    def spy_keep(self, columns):  # type: ignore[no-untyped-def]
        self.columns = self.columns[columns]
        return keep(self, columns)

    monkeypatch.setattr(blocks, "reset", spy_reset)
    monkeypatch.setattr(blocks, "step", spy_step)
    monkeypatch.setattr(blocks, "keep", spy_keep)
    run = compose(["env=gridworld", "algo.engine=torch", "agents=population",
                   "agents.num_agents=3", "agents.budget.batch_size=[24]"])  # fmt: skip
    agents = [0, 1, 2]
    engine = Engine(run, variants_of(run, agents))
    rows = engine.begin(2, initial_theta(variants_of(run, [0])[0], run), agents)
    rows.sample(rows.theta, torch.full((3,), 24), iteration=1)
    assert len(keys) == 1 and len(draws) > ENV_CHUNK, "the batch crosses a chunk's end"
    assert len(stepped[-1]) < len(stepped[0]), "the batch narrowed"
    for t, (drawn, columns) in enumerate(zip(draws, stepped, strict=True)):
        expected = uniforms64(keys[0][columns].unsqueeze(1), torch.tensor([[ENV_COUNTERS - t]]))
        assert torch.equal(drawn, expected), t


def test_only_the_modelled_families_get_torch_copies() -> None:
    assert device_family(_variants("lunarlander", 2), CPU) is None
    assert device_family(_variants("cartpole", 2), CPU) is not None
    changed = [v.__class__(**{**vars(v), "action_cost": 0.5}) for v in _variants("acrobot", 2)]
    assert device_family(changed, CPU) is None, "an action cost on discrete actions"


@pytest.mark.parametrize(
    ("name", "agents", "copies", "horizon"),
    [("cartpole", 8, 50, 500), ("pendulum", 4, 40, 200), ("gridworld", 8, 50, 50),
     ("mountaincar", 4, 20, 200), ("acrobot", 2, 20, 100)],
)  # fmt: skip
def test_both_environment_paths_give_returns_of_one_distribution(
    name: str, agents: int, copies: int, horizon: int
) -> None:
    """The same θ̃ and trajectory keys through the torch copies and through gymnasium: the mean
    returns agree within 4 standard errors of their difference."""
    returns = {}
    for path in ("auto", "gymnasium"):
        run = compose([
            f"env={name}", "agents=population", f"agents.num_agents={agents}",
            "algo.engine=torch", f"algo.envs={path}", f"env.horizon={horizon}",
        ])  # fmt: skip
        engine = Engine(run, variants_of(run, range(agents)))
        assert (engine.backend.family() is not None) == (path == "auto")
        rows = engine.begin(1, initial_theta(variants_of(run, [0])[0], run), list(range(agents)))
        batch = rows.sample(rows.theta, torch.full((agents,), copies), iteration=0)
        returns[path] = batch.returns()
        engine.close()
    device, gym = returns["auto"], returns["gymnasium"]
    error = (device.var() / len(device) + gym.var() / len(gym)).sqrt().clamp_min(1e-9)
    assert float((device.mean() - gym.mean()).abs() / error) < 4.0, (device.mean(), gym.mean())


def test_a_registered_family_is_asked_after_the_built_in_ones(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The built-in families come first, in their listed order; a registered one models what
    none of them does, and registering it twice asks it once."""
    from fedhpg.envs.device import register_device_family, registry

    monkeypatch.setattr(registry, "IMPLEMENTATIONS", list(registry.BUILT_IN))
    asked: list[int] = []
    theirs = object()

    def plugin(variants, device):
        asked.append(len(variants))
        return theirs

    assert register_device_family(plugin) is plugin
    register_device_family(plugin)
    assert tuple(registry.IMPLEMENTATIONS[:-1]) == registry.BUILT_IN
    assert registry.IMPLEMENTATIONS[-1] is plugin

    cartpoles = _variants("cartpole", 2)
    assert isinstance(device_copies(cartpoles, [1, 1], CPU), CartPoleCopies)
    assert asked == []

    class Other:
        pass

    assert device_family([Other(), Other()], CPU) is theirs
    assert asked == [2]
