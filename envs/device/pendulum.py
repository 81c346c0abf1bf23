"""Pendulum-v1 in torch: gymnasium's equations with each copy's gravity, mass, length and
action cost.

One step: the torque clipped to ±2, reward −(θ_n² + 0.1 θ̇² + 0.001 u²) with θ_n the angle
normalised into [−π, π), θ̇ += (3g/(2l) sin θ + 3/(m l²) u) dt with dt = 0.05, clipped to ±8,
then θ += θ̇ dt; never terminated, truncated at the step limit (200); starts with θ uniform in
[−π, π] and θ̇ in [−1, 1]. A variant's action cost c subtracts c·u² of the clipped torque, as
the gymnasium path's wrapper does (``envs/gym_adapter.py``). Gymnasium's ``PendulumEnv`` step
for step (``tests/test_device_envs.py``), to float32 rounding (its state is float64).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device.tensors import Params, TableFamily, TensorCopies, physics_family

DT = 0.05
MAX_SPEED = 8.0
MAX_TORQUE = 2.0
DEFAULTS = {"g": 10.0, "m": 1.0, "l": 1.0}
PHYSICS = tuple(DEFAULTS)
STEP_LIMIT = 200


def physics_of(variant: EnvVariant) -> dict[str, float] | None:
    """The variant's Pendulum constants and action cost, or None if it is not a Pendulum this
    models."""
    if getattr(variant, "env_id", None) != "Pendulum-v1":
        return None
    kwargs: dict[str, float] = dict(getattr(variant, "env_kwargs", {}))
    attributes: dict[str, float] = dict(getattr(variant, "attributes", {}))
    if not set(kwargs) <= {"g"} or not set(attributes) <= set(PHYSICS):
        return None
    constants = {**DEFAULTS, **kwargs, **attributes}
    return {
        **{name: float(constants[name]) for name in PHYSICS},
        "action_cost": float(getattr(variant, "action_cost", 0.0)),
    }


def angle_normalize(x: torch.Tensor) -> torch.Tensor:
    """x into [−π, π) (gymnasium's ``angle_normalize``)."""
    return ((x + math.pi) % (2 * math.pi)) - math.pi


class PendulumCopies(TensorCopies):
    """Pendulum copies: state [θ, θ̇] in float32."""

    state_size = 2
    reset_draws = 2

    def start(self, uniforms: torch.Tensor, p: Params) -> torch.Tensor:
        high = torch.tensor([math.pi, 1.0], dtype=uniforms.dtype, device=uniforms.device)
        return (uniforms * (2 * high) - high).T

    def advance(
        self, state: torch.Tensor, actions: torch.Tensor, p: Params, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        theta, theta_dot = state
        u = actions.reshape(-1).to(state.dtype).clamp(-MAX_TORQUE, MAX_TORQUE)
        g, m, length = p["g"], p["m"], p["l"]
        costs = angle_normalize(theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * (u**2)
        new_dot = (
            theta_dot + (3 * g / (2 * length) * torch.sin(theta) + 3.0 / (m * length**2) * u) * DT
        )
        new_dot = new_dot.clamp(-MAX_SPEED, MAX_SPEED)
        new_theta = theta + new_dot * DT
        reward = -costs.to(torch.float64) - p["action_cost"].to(torch.float64) * (u.double() ** 2)
        never = torch.zeros(theta.shape, dtype=torch.bool, device=theta.device)
        return torch.stack((new_theta, new_dot)), reward, never, never

    def observe(self, state: torch.Tensor, p: Params) -> torch.Tensor:
        theta, theta_dot = state
        return torch.stack((torch.cos(theta), torch.sin(theta), theta_dot), dim=1)


def pendulum_family(variants: Sequence[EnvVariant], device: torch.device) -> TableFamily | None:
    """The Pendulum variants' constants on ``device`` (None unless every one is a Pendulum this
    models)."""
    return physics_family(
        PendulumCopies, variants, physics_of, (*PHYSICS, "action_cost"), STEP_LIMIT, device
    )
