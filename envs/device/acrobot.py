"""Acrobot-v1 in torch: gymnasium's equations (the "book" dynamics) with each copy's link
lengths, masses, centres of mass and moment of inertia.

One step: the torque −1, 0 or +1 held for dt = 0.2 s, integrated by one classical RK4 step of
the equations of motion, both angles wrapped into [−π, π], the velocities bounded by 4π and 9π;
terminated once the tip is a link's length above the pivot (−cos θ₁ − cos(θ₁ + θ₂) > 1),
reward −1 per step and 0 on the terminating one, starts uniform in ±0.1 for all four state
variables: gymnasium's ``AcrobotEnv`` step for step (``tests/test_device_envs.py``). The
state is float32, gymnasium's float64: one step agrees to float32 rounding.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device.tensors import Params, TableFamily, TensorCopies, physics_family

DT = 0.2
GRAVITY = 9.8
MAX_VEL_1 = 4 * math.pi
MAX_VEL_2 = 9 * math.pi
TORQUES = (-1.0, 0.0, 1.0)
DEFAULTS = {
    "LINK_LENGTH_1": 1.0,
    "LINK_LENGTH_2": 1.0,
    "LINK_MASS_1": 1.0,
    "LINK_MASS_2": 1.0,
    "LINK_COM_POS_1": 0.5,
    "LINK_COM_POS_2": 0.5,
    "LINK_MOI": 1.0,
}
PHYSICS = tuple(DEFAULTS)
STEP_LIMIT = 500


def physics_of(variant: EnvVariant) -> dict[str, float] | None:
    """The variant's Acrobot constants, or None if it is not an Acrobot this models."""
    if getattr(variant, "env_id", None) != "Acrobot-v1":
        return None
    if getattr(variant, "env_kwargs", None) or getattr(variant, "action_cost", 0.0):
        return None
    attributes: dict[str, float] = dict(getattr(variant, "attributes", {}))
    if not set(attributes) <= set(PHYSICS):
        return None
    return {name: float(attributes.get(name, DEFAULTS[name])) for name in PHYSICS}


def _derivatives(s: torch.Tensor, torque: torch.Tensor, p: Params) -> torch.Tensor:
    """dS/dt of states s [4, m] under ``torque`` [m] (gymnasium's ``_dsdt``, book version)."""
    m1, m2 = p["LINK_MASS_1"], p["LINK_MASS_2"]
    l1, lc1, lc2 = p["LINK_LENGTH_1"], p["LINK_COM_POS_1"], p["LINK_COM_POS_2"]
    moi = p["LINK_MOI"]
    theta1, theta2, dtheta1, dtheta2 = s
    d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * torch.cos(theta2)) + moi + moi
    d2 = m2 * (lc2**2 + l1 * lc2 * torch.cos(theta2)) + moi
    phi2 = m2 * lc2 * GRAVITY * torch.cos(theta1 + theta2 - math.pi / 2.0)
    phi1 = (
        -m2 * l1 * lc2 * dtheta2**2 * torch.sin(theta2)
        - 2 * m2 * l1 * lc2 * dtheta2 * dtheta1 * torch.sin(theta2)
        + (m1 * lc1 + m2 * l1) * GRAVITY * torch.cos(theta1 - math.pi / 2)
        + phi2
    )
    ddtheta2 = (torque + d2 / d1 * phi1 - m2 * l1 * lc2 * dtheta1**2 * torch.sin(theta2) - phi2) / (
        m2 * lc2**2 + moi - d2**2 / d1
    )
    ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
    return torch.stack((dtheta1, dtheta2, ddtheta1, ddtheta2))


def _wrap(x: torch.Tensor) -> torch.Tensor:
    """x wrapped into [−π, π] by whole turns, for any magnitude. Up to three turns are
    subtracted one at a time, as gymnasium's ``wrap`` does (so every angle a step from a
    bounded state reaches rounds as there); an angle still outside (a state set with extreme
    velocities, say) is reduced by ``torch.remainder``."""
    for _ in range(3):
        x = torch.where(x > math.pi, x - 2 * math.pi, x)
        x = torch.where(x < -math.pi, x + 2 * math.pi, x)
    outside = (x > math.pi) | (x < -math.pi)
    return torch.where(outside, torch.remainder(x + math.pi, 2 * math.pi) - math.pi, x)


class AcrobotCopies(TensorCopies):
    """Acrobot copies: state [θ₁, θ₂, θ̇₁, θ̇₂] in float32."""

    state_size = 4
    reset_draws = 4

    def start(self, uniforms: torch.Tensor, p: Params) -> torch.Tensor:
        return uniforms.T * 0.2 - 0.1

    def advance(
        self, state: torch.Tensor, actions: torch.Tensor, p: Params, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        torque = (actions.to(state.dtype) - 1.0).reshape(-1)  # 0, 1, 2 -> −1, 0, +1
        half = DT / 2.0
        k1 = _derivatives(state, torque, p)
        k2 = _derivatives(state + half * k1, torque, p)
        k3 = _derivatives(state + half * k2, torque, p)
        k4 = _derivatives(state + DT * k3, torque, p)
        after = state + DT / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        theta1, theta2 = _wrap(after[0]), _wrap(after[1])
        dtheta1 = after[2].clamp(-MAX_VEL_1, MAX_VEL_1)
        dtheta2 = after[3].clamp(-MAX_VEL_2, MAX_VEL_2)
        state = torch.stack((theta1, theta2, dtheta1, dtheta2))
        terminated = -torch.cos(theta1) - torch.cos(theta2 + theta1) > 1.0
        reward = torch.where(terminated, 0.0, -1.0).to(torch.float64)
        return state, reward, terminated, torch.zeros_like(terminated)

    def observe(self, state: torch.Tensor, p: Params) -> torch.Tensor:
        theta1, theta2, dtheta1, dtheta2 = state
        return torch.stack(
            (
                torch.cos(theta1),
                torch.sin(theta1),
                torch.cos(theta2),
                torch.sin(theta2),
                dtheta1,
                dtheta2,
            ),
            dim=1,
        )


def acrobot_family(variants: Sequence[EnvVariant], device: torch.device) -> TableFamily | None:
    """The Acrobot variants' constants on ``device`` (None unless every one is an Acrobot this
    models)."""
    return physics_family(AcrobotCopies, variants, physics_of, PHYSICS, STEP_LIMIT, device)
