"""MountainCar-v0 in torch: gymnasium's equations with each copy's engine force and gravity.

One step: v += (a − 1)·force − cos(3x)·gravity, clipped to ±0.07; x += v, clipped to
[−1.2, 0.6], and v = 0 where the car stands at the left wall moving left; terminated once
x ≥ 0.5 with v ≥ the goal velocity (0), reward −1 per step, truncated at the step limit (200);
starts at x uniform in [−0.6, −0.4] at rest. Gymnasium's ``MountainCarEnv`` step for step
(``tests/test_device_envs.py``), to float32 rounding (its state is float64).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device.tensors import Params, TableFamily, TensorCopies, physics_family

MIN_POSITION = -1.2
MAX_POSITION = 0.6
MAX_SPEED = 0.07
GOAL_POSITION = 0.5
DEFAULTS = {"force": 0.001, "gravity": 0.0025, "goal_velocity": 0.0}
PHYSICS = tuple(DEFAULTS)
STEP_LIMIT = 200


def physics_of(variant: EnvVariant) -> dict[str, float] | None:
    """The variant's MountainCar constants, or None if it is not a MountainCar this models."""
    if getattr(variant, "env_id", None) != "MountainCar-v0":
        return None
    if getattr(variant, "action_cost", 0.0):
        return None
    kwargs: dict[str, float] = dict(getattr(variant, "env_kwargs", {}))
    attributes: dict[str, float] = dict(getattr(variant, "attributes", {}))
    if not set(kwargs) <= {"goal_velocity"} or not set(attributes) <= set(PHYSICS):
        return None
    constants = {**DEFAULTS, **kwargs, **attributes}
    return {name: float(constants[name]) for name in PHYSICS}


class MountainCarCopies(TensorCopies):
    """MountainCar copies: state [x, v] in float32."""

    state_size = 2
    reset_draws = 1

    def start(self, uniforms: torch.Tensor, p: Params) -> torch.Tensor:
        position = uniforms[:, 0] * 0.2 - 0.6
        return torch.stack((position, torch.zeros_like(position)))

    def advance(
        self, state: torch.Tensor, actions: torch.Tensor, p: Params, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        position, velocity = state
        push = actions.reshape(-1).to(state.dtype) - 1.0
        velocity = velocity + push * p["force"] + torch.cos(3 * position) * (-p["gravity"])
        velocity = velocity.clamp(-MAX_SPEED, MAX_SPEED)
        position = (position + velocity).clamp(MIN_POSITION, MAX_POSITION)
        velocity = torch.where((position == MIN_POSITION) & (velocity < 0), 0.0, velocity)
        terminated = (position >= GOAL_POSITION) & (velocity >= p["goal_velocity"])
        reward = torch.full(position.shape, -1.0, dtype=torch.float64, device=position.device)
        return torch.stack((position, velocity)), reward, terminated, torch.zeros_like(terminated)

    def observe(self, state: torch.Tensor, p: Params) -> torch.Tensor:
        return state.T.contiguous()


def mountaincar_family(variants: Sequence[EnvVariant], device: torch.device) -> TableFamily | None:
    """The MountainCar variants' constants on ``device`` (None unless every one is a
    MountainCar this models)."""
    return physics_family(MountainCarCopies, variants, physics_of, PHYSICS, STEP_LIMIT, device)
