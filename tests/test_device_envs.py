"""The torch environment families against gymnasium's own environments, step for step.

For variants drawn by the families (every physical constant changed), each copy is put in a
random state, both take the same action, and the next state, reward and termination agree (to
float32 rounding: gymnasium steps in float64). Truncation comes at the variant's step limit,
and a copy's reset is a function of its own stream alone.
"""

from __future__ import annotations

import numpy as np
import torch

from fedhpg.common.runtime.cli import compose
from fedhpg.common.variants import variants_of
from fedhpg.envs.device import device_copies
from fedhpg.envs.device.cartpole import CartPoleCopies

CPU = torch.device("cpu")


class _Stream:
    def __init__(self, uniforms: torch.Tensor) -> None:
        self.values = uniforms

    def uniforms(self, count: int) -> torch.Tensor:
        return self.values[:, :count]

    def seeds(self) -> list[int]:
        return [0] * len(self.values)


def _cartpoles(count: int) -> list:
    run = compose(["env=cartpole", "env.level=1.0", f"agents.num_agents={count}",
                   "agents.budget.batch_size=[1]", "agents.speeds=[1]",
                   "agents.step_delays_s=[0]"])  # fmt: skip
    variants = variants_of(run, list(range(count)))
    return [variants[k] for k in range(count)]


def test_cartpole_steps_like_gymnasiums_for_every_variant() -> None:
    variants = _cartpoles(12)
    copies = device_copies(variants, [20] * 12, CPU)
    assert isinstance(copies, CartPoleCopies)
    rng = np.random.default_rng(0)
    columns = torch.arange(copies.num_copies)
    low, high = [-2.3, -2.0, -0.2, -2.5], [2.3, 2.0, 0.2, 2.5]
    states = rng.uniform(low, high, size=(copies.num_copies, 4))
    actions = rng.integers(0, 2, size=copies.num_copies)
    copies.state[:] = torch.from_numpy(states.T).float()
    copies.steps[:] = 0
    step = copies.step(torch.from_numpy(actions), columns)
    for n in range(copies.num_copies):
        variant = variants[n // 20]
        env = variant.make_env().unwrapped
        env.reset(seed=0)
        env.state = states[n].astype(np.float32).astype(np.float64)  # the copy's float32 start
        obs, reward, terminated, _, _ = env.step(int(actions[n]))
        np.testing.assert_allclose(step.obs[n].numpy(), obs, rtol=1e-5, atol=1e-6)
        assert float(step.reward[n]) == reward
        assert bool(step.terminated[n]) == terminated
    assert bool(step.terminated.any()) and not bool(step.terminated.all())


def test_cartpole_truncates_at_the_step_limit_and_resets_from_its_stream() -> None:
    variants = _cartpoles(2)
    copies = device_copies(variants, [3, 3], CPU)
    assert copies is not None
    columns = torch.arange(6)
    uniforms = torch.rand(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    first = copies.reset(columns, _Stream(uniforms))
    assert float(first.abs().max()) <= 0.05
    torch.testing.assert_close(first, (uniforms * 0.1 - 0.05).float())
    again = copies.reset(columns[3:], _Stream(uniforms[3:]))
    assert torch.equal(again, first[3:]), "a copy's start depends on its own draws alone"
    copies.state.zero_()  # upright and still: only the step limit can end it
    copies.steps[:] = 499
    step = copies.step(torch.tensor([0, 1, 0, 1, 0, 1]), columns)
    assert bool(step.truncated.all()) and not bool(step.terminated.any())


def test_only_the_modelled_cartpoles_get_torch_copies() -> None:
    run = compose(["env=acrobot", "agents.num_agents=2", "agents.budget.batch_size=[1]",
                   "agents.speeds=[1]", "agents.step_delays_s=[0]"])  # fmt: skip
    assert device_copies(list(variants_of(run, [0, 1]).values()), [2, 2], CPU) is None
    assert device_copies(_cartpoles(2), [2, 2], CPU) is not None
