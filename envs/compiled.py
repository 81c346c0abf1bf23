"""Compiled (numba) dynamics of the families that have them, for the compiled backend
(common/learning/batched/kernels.py), which steps one copy at a time inside a kernel.

CartPole: :func:`fedhpg.envs.device.cartpole.cartpole_update` itself, compiled, on one copy's
float64 state with its variant's constants in a row of :data:`CARTPOLE_PHYSICS` order.
Imports numba: only the compiled backend imports this module.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import cast

import numpy as np
from numba import njit

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device.cartpole import (
    DEFAULTS,
    PHYSICS,
    STEP_LIMIT,
    THETA_LIMIT,
    X_LIMIT,
    cartpole_update,
)
from fedhpg.envs.device.cartpole import physics_of as cartpole_physics

THETA_THRESHOLD = THETA_LIMIT
X_THRESHOLD = X_LIMIT
CARTPOLE_STEP_LIMIT = STEP_LIMIT
"""CartPole-v1's truncation (the only limit the compiled backend models)."""
CARTPOLE_PHYSICS = PHYSICS
CARTPOLE_DEFAULTS = tuple(DEFAULTS[name] for name in CARTPOLE_PHYSICS)


def cartpole_table(variants: Sequence[EnvVariant]) -> np.ndarray | None:
    """[A, 7] float64 constants of the variants in CARTPOLE_PHYSICS order, or None unless
    every variant is a CartPole that the compiled dynamics model."""
    rows = []
    for variant in variants:
        physics = cartpole_physics(variant)
        if physics is None or getattr(variant, "step_limit", 0) not in (0, STEP_LIMIT):
            return None
        rows.append([physics[name] for name in CARTPOLE_PHYSICS])
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), len(CARTPOLE_PHYSICS))


_update = cast(
    Callable[..., tuple[float, float, float, float]],
    njit(cache=True, error_model="numpy", inline="always")(cartpole_update),
)


@njit(cache=True, error_model="numpy", inline="always")
def cartpole_step(state: np.ndarray, copy: int, physics: np.ndarray, action: int) -> bool:
    """Advance ``state[copy]`` = [x, ẋ, θ, θ̇] (float64) in place by one Euler step; terminated?
    (Indexed rather than sliced: a view per step would cost a reference count each time.)"""
    theta = state[copy, 2]
    force = physics[6] if action == 1 else -physics[6]
    x, x_dot, theta, theta_dot = _update(
        state[copy, 0], state[copy, 1], theta, state[copy, 3], math.cos(theta), math.sin(theta),
        force, physics[0], physics[2], physics[3], physics[4], physics[5],
    )  # fmt: skip
    state[copy, 0], state[copy, 1], state[copy, 2], state[copy, 3] = x, x_dot, theta, theta_dot
    return (
        x < -X_THRESHOLD or x > X_THRESHOLD or theta < -THETA_THRESHOLD or theta > THETA_THRESHOLD
    )
