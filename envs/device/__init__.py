"""Environment copies that live in torch tensors on the engine's device.

A family with a torch implementation steps every copy of every agent's variant as elementwise
tensor arithmetic, with each copy's physical constants in a tensor of its own, so a whole
federation's environments can live on a GPU beside its policies. :func:`device_copies` picks
the implementation for a set of variants, or None where a family has none (those step through
gymnasium on the CPU: ``fedhpg.common.engine.copies``).

Randomness comes from the caller: :class:`ResetStream` hands each copy's reset its own uniforms,
so an environment never owns a generator and a copy's episode depends on its stream alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

import torch

from fedhpg.envs.base import EnvVariant


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

    def reset(self, columns: torch.Tensor, stream: ResetStream) -> torch.Tensor:
        """Start an episode in copies ``columns``; their first observations."""
        ...

    def step(self, actions: torch.Tensor, columns: torch.Tensor | None) -> CopyStep:
        """One action per copy of ``columns`` (the others are left as they are; None: every
        copy)."""
        ...


def device_copies(
    variants: Sequence[EnvVariant], counts: Sequence[int], device: torch.device
) -> DeviceCopies | None:
    """``counts[i]`` copies of ``variants[i]`` each, on ``device``, where every variant's family
    has a torch implementation (else None)."""
    from fedhpg.envs.device.cartpole import CartPoleCopies

    return CartPoleCopies.of(variants, counts, device)
