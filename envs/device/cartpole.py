"""CartPole-v1 in torch: gymnasium's equations with every physical constant per copy.

Euler integration with τ = 0.02, failure beyond 12° or 2.4, reward 1 per step including the
failing one, truncation at the variant's step limit, starts uniform in ±0.05: gymnasium's
``CartPoleEnv`` step for step (``tests/test_device_envs.py`` checks state, reward and
termination against it for sampled variants). The state is float32, gymnasium's is float64:
one step agrees to float32 rounding, and long episodes drift apart as any two float
precisions do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeVar

import torch

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device import CopyStep, ResetStream

TAU = 0.02
THETA_LIMIT = 12 * 2 * math.pi / 360
X_LIMIT = 2.4
PHYSICS = (
    "gravity",
    "masscart",
    "masspole",
    "total_mass",
    "length",
    "polemass_length",
    "force_mag",
)
DEFAULTS = {
    "gravity": 9.8,
    "masscart": 1.0,
    "masspole": 0.1,
    "total_mass": 1.1,
    "length": 0.5,
    "polemass_length": 0.05,
    "force_mag": 10.0,
}
STEP_LIMIT = 500
Value = TypeVar("Value", float, torch.Tensor)


def physics_of(variant: EnvVariant) -> dict[str, float] | None:
    """The variant's CartPole constants, or None if it is not a CartPole this models."""
    if getattr(variant, "env_id", None) != "CartPole-v1":
        return None
    if getattr(variant, "env_kwargs", None) or getattr(variant, "action_cost", 0.0):
        return None
    attributes: dict[str, float] = dict(getattr(variant, "attributes", {}))
    if not set(attributes) <= set(PHYSICS):
        return None
    return {name: float(attributes.get(name, DEFAULTS[name])) for name in PHYSICS}


def cartpole_update(
    x: Value,
    x_dot: Value,
    theta: Value,
    theta_dot: Value,
    costheta: Value,
    sintheta: Value,
    force: Value,
    gravity: Value,
    masspole: Value,
    total_mass: Value,
    length: Value,
    polemass_length: Value,
) -> tuple[Value, Value, Value, Value]:
    """One Euler step of gymnasium's CartPole equations, in its order of operations. Plain
    arithmetic, so the one definition steps torch tensors (every copy at once, here) and
    numba's float64 scalars (one copy at a time, ``fedhpg.envs.compiled``)."""
    temp = (force + polemass_length * (theta_dot * theta_dot) * sintheta) / total_mass
    thetaacc = (gravity * sintheta - costheta * temp) / (
        length * (4.0 / 3.0 - masspole * (costheta * costheta) / total_mass)
    )
    xacc = temp - polemass_length * thetaacc * costheta / total_mass
    return (
        x + TAU * x_dot,
        x_dot + TAU * xacc,
        theta + TAU * theta_dot,
        theta_dot + TAU * thetaacc,
    )


class CartPoleCopies:
    """``counts[i]`` CartPole copies of variant i, in float32 tensors on one device."""

    def __init__(
        self,
        physics: Sequence[dict[str, float]],
        counts: Sequence[int],
        limits: Sequence[int],
        device: torch.device,
    ) -> None:
        self.device = device
        repeats = torch.tensor(list(counts), dtype=torch.int64)
        self.num_copies = int(repeats.sum())
        self.params = {
            name: torch.tensor([p[name] for p in physics], dtype=torch.float32)
            .repeat_interleave(repeats)
            .to(device)
            for name in PHYSICS
        }
        self.limit = torch.tensor(list(limits)).repeat_interleave(repeats).to(device)
        self.state = torch.zeros(4, self.num_copies, dtype=torch.float32, device=device)
        self.steps = torch.zeros(self.num_copies, dtype=torch.int64, device=device)

    @classmethod
    def of(
        cls, variants: Sequence[EnvVariant], counts: Sequence[int], device: torch.device
    ) -> CartPoleCopies | None:
        physics = [physics_of(v) for v in variants]
        if not variants or any(p is None for p in physics):
            return None
        limits = [int(getattr(v, "step_limit", 0) or STEP_LIMIT) for v in variants]
        return cls([p for p in physics if p is not None], counts, limits, device)

    def reset(self, columns: torch.Tensor, stream: ResetStream) -> torch.Tensor:
        start = stream.uniforms(4).to(device=self.device).T * 0.1 - 0.05
        self.state[:, columns] = start.to(torch.float32)
        self.steps[columns] = 0
        return self.state[:, columns].T.contiguous()

    def step(self, actions: torch.Tensor, columns: torch.Tensor | None) -> CopyStep:
        if columns is None:
            p, state, steps_before, limit = self.params, self.state, self.steps, self.limit
        else:
            p = {name: values[columns] for name, values in self.params.items()}
            state, steps_before, limit = (
                self.state[:, columns],
                self.steps[columns],
                self.limit[columns],
            )
        x, x_dot, theta, theta_dot = state
        force = torch.where(actions == 1, p["force_mag"], -p["force_mag"])
        state = torch.stack(cartpole_update(
            x, x_dot, theta, theta_dot, torch.cos(theta), torch.sin(theta), force,
            p["gravity"], p["masspole"], p["total_mass"], p["length"], p["polemass_length"],
        ))  # fmt: skip
        steps = steps_before + 1
        if columns is None:
            self.state, self.steps = state, steps
        else:
            self.state[:, columns] = state
            self.steps[columns] = steps
        terminated = (state[0].abs() > X_LIMIT) | (state[2].abs() > THETA_LIMIT)
        count = state.shape[1]
        return CopyStep(
            obs=state.T.contiguous(),
            reward=torch.ones(count, dtype=torch.float64, device=self.device),
            terminated=terminated,
            truncated=steps >= limit,
            success=torch.zeros(count, dtype=torch.bool, device=self.device),
        )
