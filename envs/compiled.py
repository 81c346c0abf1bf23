"""Compiled (numba) dynamics of the families that have them, for the compiled engine
(common/batched/kernels.py), which steps one copy at a time inside a kernel.

CartPole: :class:`~fedhpg.envs.multi.CartPoleMulti`'s equations, operation for operation (so
the same floats: tests/test_compiled_engine.py steps both from the same states and actions
and compares bit for bit), on one copy's state with its variant's constants in a row of
:data:`CARTPOLE_PHYSICS` order. Imports numba: only the compiled engine imports this module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.multi import CARTPOLE_PHYSICS, CartPoleMulti, cartpole_physics

TAU = CartPoleMulti.TAU
THETA_THRESHOLD = CartPoleMulti.THETA_THRESHOLD
X_THRESHOLD = CartPoleMulti.X_THRESHOLD
CARTPOLE_STEP_LIMIT = 500
"""CartPole-v1's truncation (the only limit :func:`cartpole_physics` accepts)."""
_DEFAULTS = {
    "gravity": 9.8,
    "masscart": 1.0,
    "masspole": 0.1,
    "total_mass": 1.1,
    "length": 0.5,
    "polemass_length": 0.05,
    "force_mag": 10.0,
}
"""gymnasium CartPole-v1's constants (tests check them against gymnasium's)."""
CARTPOLE_DEFAULTS = tuple(_DEFAULTS[name] for name in CARTPOLE_PHYSICS)


def cartpole_table(variants: Sequence[EnvVariant]) -> np.ndarray | None:
    """[A, 7] float64 constants of the variants in CARTPOLE_PHYSICS order, or None unless
    every variant is a CartPole that the compiled dynamics model."""
    rows = []
    for variant in variants:
        physics = cartpole_physics(variant)
        if physics is None:
            return None
        rows.append([physics.get(name, _DEFAULTS[name]) for name in CARTPOLE_PHYSICS])
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), len(CARTPOLE_PHYSICS))


@njit(cache=True, error_model="numpy", inline="always")
def cartpole_step(state: np.ndarray, copy: int, physics: np.ndarray, action: int) -> bool:
    """Advance ``state[copy]`` = [x, ẋ, θ, θ̇] (float64) in place by one Euler step; terminated?
    (Indexed rather than sliced: a view per step would cost a reference count each time.)"""
    gravity, masspole, total_mass = physics[0], physics[2], physics[3]
    length, polemass_length, force_mag = physics[4], physics[5], physics[6]
    x, x_dot, theta, theta_dot = state[copy, 0], state[copy, 1], state[copy, 2], state[copy, 3]
    force = force_mag if action == 1 else -force_mag
    costheta = math.cos(theta)
    sintheta = math.sin(theta)
    temp = (force + polemass_length * (theta_dot * theta_dot) * sintheta) / total_mass
    thetaacc = (gravity * sintheta - costheta * temp) / (
        length * (4.0 / 3.0 - masspole * (costheta * costheta) / total_mass)
    )
    xacc = temp - polemass_length * thetaacc * costheta / total_mass
    x = x + TAU * x_dot
    x_dot = x_dot + TAU * xacc
    theta = theta + TAU * theta_dot
    theta_dot = theta_dot + TAU * thetaacc
    state[copy, 0], state[copy, 1], state[copy, 2], state[copy, 3] = x, x_dot, theta, theta_dot
    return (
        x < -X_THRESHOLD or x > X_THRESHOLD or theta < -THETA_THRESHOLD or theta > THETA_THRESHOLD
    )
