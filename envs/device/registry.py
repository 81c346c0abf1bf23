"""Which torch implementation models a set of variants: the built-in families, by an explicit
list, then those a plugin registers.

:func:`device_family` asks each implementation in turn and takes the first that models all
the variants.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device.acrobot import acrobot_family
from fedhpg.envs.device.cartpole import cartpole_family
from fedhpg.envs.device.gridworld import gridworld_family
from fedhpg.envs.device.mountaincar import mountaincar_family
from fedhpg.envs.device.pendulum import pendulum_family
from fedhpg.envs.device.protocols import DeviceCopies, DeviceFamily, Implementation

BUILT_IN: tuple[Implementation, ...] = (
    acrobot_family,
    cartpole_family,
    gridworld_family,
    mountaincar_family,
    pendulum_family,
)
"""The families with a torch implementation in this package, one module each."""

IMPLEMENTATIONS: list[Implementation] = list(BUILT_IN)
"""Every implementation :func:`device_family` asks, in order: the built-in ones, then the
registered ones."""


def register_device_family(implementation: Implementation) -> Implementation:
    """Add a torch implementation (a plugin's): :func:`device_family` asks it after the
    built-in ones and those registered before it."""
    if implementation not in IMPLEMENTATIONS:
        IMPLEMENTATIONS.append(implementation)
    return implementation


def device_family(variants: Sequence[EnvVariant], device: torch.device) -> DeviceFamily | None:
    """The torch implementation's table of ``variants`` on ``device``, or None where no
    implementation models every one of them."""
    if not variants:
        return None
    for implementation in IMPLEMENTATIONS:
        family = implementation(variants, device)
        if family is not None:
            return family
    return None


def device_copies(
    variants: Sequence[EnvVariant], counts: Sequence[int], device: torch.device
) -> DeviceCopies | None:
    """``counts[i]`` copies of ``variants[i]`` each, on ``device`` (None: no torch
    implementation models them)."""
    family = device_family(variants, device)
    if family is None:
        return None
    rows = torch.arange(len(variants), device=device)
    return family.copies(rows, torch.tensor(list(counts), dtype=torch.int64, device=device))
