"""What a torch family of environment copies offers the engine: the protocols every family
implements and the shape of one step.

A leaf module (torch and ``fedhpg.envs.base`` alone): the families, their shared
bookkeeping (``fedhpg.envs.device.tensors``), the registry and the engine import it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
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

    def keep(self, columns: torch.Tensor) -> None:
        """Keep only the copies ``columns`` (increasing), renumbered 0 … m − 1 in order."""
        ...


class DeviceFamily(Protocol):
    """The constants of some variants of one family, as tables on one device."""

    device: torch.device
    step_noise: int
    """Uniforms each of its copies' steps takes (0: deterministic steps)."""

    def copies(self, rows: torch.Tensor, counts: torch.Tensor) -> DeviceCopies:
        """``counts[i]`` copies of variant ``rows[i]`` (positions in the variants it was made
        of; int64 tensors on the device), in that order."""
        ...


Implementation = Callable[[Sequence[EnvVariant], torch.device], DeviceFamily | None]
"""(variants, device) -> their table, or None where the implementation does not model them
all (another family, or a variant changed in a way it does not model)."""
