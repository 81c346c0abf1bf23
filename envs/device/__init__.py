"""Environment copies that live in torch tensors on the engine's device.

A family with a torch implementation steps every copy of every agent's variant as elementwise
tensor arithmetic, each copy's constants (masses, lengths, gravity, slip, its grid's tables) in
tensors of their own, so a whole federation's environments live on a GPU beside its policies.

- :func:`device_family` turns the variants of one engine into a :class:`DeviceFamily`: their
  constants as a table on the device, built once; it hands out :class:`DeviceCopies` of any of
  them (``copies(rows, counts)``) without touching the host again. None where the family has
  no torch implementation (those step through gymnasium on the CPU:
  ``fedhpg.common.engine.copies``).
- Implementations register with :func:`register_device_family`: CartPole, Acrobot, Pendulum,
  MountainCar and GridWorld are built in, one module each; each is checked
  step for step against its gymnasium environment (``tests/test_device_envs.py``).

Randomness comes from the caller: :class:`ResetStream` hands each copy's reset its own
uniforms, and a family whose steps are random (GridWorld's slip) asks for ``step_noise``
uniforms per copy and step, so an environment never owns a generator and a copy's episode
depends on its own stream alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol

import torch

from fedhpg.envs.base import EnvVariant


def put_distinct(
    target: torch.Tensor,
    index: torch.Tensor | tuple[torch.Tensor | slice, ...],
    values: torch.Tensor | float,
) -> None:
    """``target[index] = values`` where ``index`` names no position twice.

    Such a write has one result whatever order a device makes it in. Torch's deterministic
    algorithms (the engine runs under them off the CPU) cannot know the positions are
    distinct and sort the indices of every indexed write on a GPU first; this makes the write
    without that sort (deterministic mode stays on for everything else)."""
    if target.device.type == "cpu" or not torch.are_deterministic_algorithms_enabled():
        target[index] = values
        return
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(False)
    try:
        target[index] = values
    finally:
        torch.use_deterministic_algorithms(True, warn_only=warn_only)


class ResetStream(Protocol):
    """The randomness of one reset of some copies (one row of draws per copy)."""

    def uniforms(self, count: int) -> torch.Tensor:
        """``count`` uniforms in [0, 1) per copy, float64 [M, count]."""
        ...

    def seeds(self) -> list[int]:
        """One 63-bit seed per copy (for environments that seed their own generator)."""
        ...


class CopyStep(NamedTuple):
    """One step of M copies; every tensor has leading dimension M."""

    obs: torch.Tensor
    reward: torch.Tensor  # float64
    terminated: torch.Tensor  # bool
    truncated: torch.Tensor  # bool
    success: torch.Tensor  # bool


class DeviceCopies(Protocol):
    """Copies of several variants in tensors on one device, stepped as one batch."""

    num_copies: int
    device: torch.device
    step_noise: int
    """Uniforms each copy draws per step (0: deterministic steps)."""

    def reset(self, columns: torch.Tensor, stream: ResetStream) -> torch.Tensor:
        """Start an episode in copies ``columns``; their first observations."""
        ...

    def step(
        self, actions: torch.Tensor, columns: torch.Tensor | None, noise: torch.Tensor | None
    ) -> CopyStep:
        """One action per copy of ``columns`` (the others are left as they are; None: every
        copy); ``noise`` [M, step_noise] float64 uniforms of those copies (None when
        ``step_noise`` is 0)."""
        ...


class DeviceFamily(Protocol):
    """The constants of some variants of one family, as tables on one device."""

    device: torch.device

    def copies(self, rows: torch.Tensor, counts: torch.Tensor) -> DeviceCopies:
        """``counts[i]`` copies of variant ``rows[i]`` (positions in the variants it was made
        of; int64 tensors on the device), in that order."""
        ...


Implementation = Callable[[Sequence[EnvVariant], torch.device], DeviceFamily | None]
"""(variants, device) -> their table, or None where the implementation does not model them
all (another family, or a variant changed in a way it does not model)."""

IMPLEMENTATIONS: list[Implementation] = []


def register_device_family(implementation: Implementation) -> Implementation:
    """Add a torch implementation (a plugin's included): :func:`device_family` asks every
    registered one in turn and takes the first that models all the variants."""
    if implementation not in IMPLEMENTATIONS:
        IMPLEMENTATIONS.append(implementation)
    return implementation


def device_family(variants: Sequence[EnvVariant], device: torch.device) -> DeviceFamily | None:
    """The torch implementation's table of ``variants`` on ``device``, or None where no
    registered implementation models every one of them."""
    from fedhpg.envs.device import (  # noqa: F401  (they register themselves)
        acrobot,
        cartpole,
        gridworld,
        mountaincar,
        pendulum,
    )

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
