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
from fedhpg.envs.device.tensors import Params, TableFamily, TensorCopies, physics_family

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


class CartPoleCopies(TensorCopies):
    """CartPole copies: state [x, ẋ, θ, θ̇] in float32, each copy's constants in ``params``."""

    state_size = 4
    reset_draws = 4

    def start(self, uniforms: torch.Tensor, p: Params) -> torch.Tensor:
        return uniforms.T * 0.1 - 0.05

    def advance(
        self, state: torch.Tensor, actions: torch.Tensor, p: Params, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        x, x_dot, theta, theta_dot = state
        force = torch.where(actions == 1, p["force_mag"], -p["force_mag"])
        state = torch.stack(cartpole_update(
            x, x_dot, theta, theta_dot, torch.cos(theta), torch.sin(theta), force,
            p["gravity"], p["masspole"], p["total_mass"], p["length"], p["polemass_length"],
        ))  # fmt: skip
        terminated = (state[0].abs() > X_LIMIT) | (state[2].abs() > THETA_LIMIT)
        count = state.shape[1]
        reward = torch.ones(count, dtype=torch.float64, device=state.device)
        return state, reward, terminated, torch.zeros_like(terminated)

    def observe(self, state: torch.Tensor, p: Params) -> torch.Tensor:
        return state.T.contiguous()


def cartpole_family(variants: Sequence[EnvVariant], device: torch.device) -> TableFamily | None:
    """The CartPole variants' constants on ``device`` (None unless every one is a CartPole
    this models)."""
    return physics_family(CartPoleCopies, variants, physics_of, PHYSICS, STEP_LIMIT, device)
