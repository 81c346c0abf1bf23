"""Blocks of environment copies the sampler steps: one block per row, its trajectories.

Two paths behind one interface. A family with a torch implementation
(:func:`fedhpg.envs.device.device_family`, the engine's variants' constants as tables on its
device) keeps every copy in tensors on the engine's device: nothing crosses to the host while
it steps. Any other family (or every family, with ``algo.envs=gymnasium``) steps through its
variants' gymnasium batch environments on the CPU, one per block, observations and actions
converted at the boundary.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import gymnasium as gym
import numpy as np
import torch

from fedhpg.common.randomness import seeds, uniforms64
from fedhpg.envs.base import BatchEnv
from fedhpg.envs.device import CopyStep, DeviceCopies, DeviceFamily


class KeyedReset:
    """The reset stream of copies with trajectory keys ``keys`` (reset draws use negative
    counters, which no action draw uses)."""

    def __init__(self, keys: torch.Tensor) -> None:
        self.keys = keys

    def uniforms(self, count: int) -> torch.Tensor:
        counters = -1 - torch.arange(count, device=self.keys.device)
        return uniforms64(self.keys.unsqueeze(1), counters.unsqueeze(0))

    def seeds(self) -> list[int]:
        return seeds(self.keys, -1)


class Copies(Protocol):
    """Blocks of copies, block b columns ``offsets[b]:offsets[b + 1]``."""

    offsets: torch.Tensor
    step_noise: int
    """Uniforms each copy's environment draws per step (0: none)."""
    any_copies: bool
    """Whether :meth:`step` takes any subset of the copies (else whole blocks only)."""

    def reset(self, blocks: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
        """Start an episode in every copy of ``blocks``, their copies' keys ``keys``; the
        first observations of those copies, in order."""
        ...

    def step(
        self,
        actions: torch.Tensor,
        blocks: torch.Tensor,
        columns: torch.Tensor | None,
        noise: torch.Tensor | None = None,
    ) -> CopyStep:
        """One action per copy in ``columns`` (None: every copy), ``blocks`` the blocks they
        belong to (whole blocks unless :attr:`any_copies`); ``noise`` [copies, step_noise]
        their environments' uniforms (None when none)."""
        ...

    def close(self) -> None: ...


def columns_of(offsets: torch.Tensor, blocks: torch.Tensor) -> torch.Tensor:
    """The columns of ``blocks`` (increasing), in order."""
    starts, ends = offsets[blocks], offsets[blocks + 1]
    sizes = ends - starts
    first = torch.repeat_interleave(starts - torch.cumsum(sizes, 0) + sizes, sizes)
    return first + torch.arange(int(sizes.sum()), device=offsets.device)


class DeviceBlocks:
    """Blocks over a family's torch copies."""

    def __init__(self, copies: DeviceCopies, offsets: torch.Tensor) -> None:
        self.copies = copies
        self.offsets = offsets.to(copies.device)
        self.step_noise = int(copies.step_noise)
        self.any_copies = True

    def reset(self, blocks: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
        return self.copies.reset(columns_of(self.offsets, blocks), KeyedReset(keys))

    def step(
        self,
        actions: torch.Tensor,
        blocks: torch.Tensor,
        columns: torch.Tensor | None,
        noise: torch.Tensor | None = None,
    ) -> CopyStep:
        return self.copies.step(actions, columns, noise)

    def close(self) -> None:
        pass


class GymBlocks:
    """Blocks over gymnasium batch environments, one per block, on the CPU."""

    step_noise = 0  # gymnasium environments draw from their own generators
    any_copies = False  # a batch environment steps all its copies

    def __init__(self, envs: Sequence[BatchEnv], device: torch.device) -> None:
        self.envs = list(envs)
        counts = torch.tensor([env.num_envs for env in self.envs], dtype=torch.int64)
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)]).to(device)
        self.device = device
        space = self.envs[0].single_action_space
        self.discrete = isinstance(space, gym.spaces.Discrete)

    def reset(self, blocks: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
        block_seeds = seeds(keys, -1)
        sizes = self.offsets[blocks + 1] - self.offsets[blocks]
        starts = (torch.cumsum(sizes, 0) - sizes).tolist()
        parts = [
            np.asarray(self.envs[b].reset(seed=block_seeds[start]))
            for b, start in zip(blocks.tolist(), starts, strict=True)
        ]
        return torch.from_numpy(np.concatenate(parts)).to(self.device)

    def step(
        self,
        actions: torch.Tensor,
        blocks: torch.Tensor,
        columns: torch.Tensor | None,
        noise: torch.Tensor | None = None,
    ) -> CopyStep:
        chosen = actions.cpu().numpy()
        parts, at = [], 0
        for b in blocks.tolist():
            env = self.envs[b]
            parts.append(env.step(chosen[at : at + env.num_envs]))
            at += env.num_envs
        cat = np.concatenate

        def tensor(values: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(values).to(self.device)

        return CopyStep(
            obs=tensor(cat([p.obs for p in parts])),
            reward=tensor(cat([p.reward for p in parts]).astype(np.float64)),
            terminated=tensor(cat([p.terminated for p in parts]).astype(bool)),
            truncated=tensor(cat([p.truncated for p in parts]).astype(bool)),
            success=tensor(cat([p.success for p in parts]).astype(bool)),
        )

    def close(self) -> None:
        pass  # the environments belong to the engine's cache


EnvSource = Callable[[int, int], BatchEnv]
"""(row's agent index, copies) -> that agent's batch environment of so many copies."""


def make_copies(
    family: DeviceFamily | None,
    rows: torch.Tensor,
    counts: torch.Tensor,
    batch_env: EnvSource,
    agents: Sequence[int],
    device: torch.device,
) -> Copies:
    """Blocks of ``counts[i]`` copies of agent ``agents[i]``'s variant: on the device from
    ``family`` (the variants' table; ``rows[i]``: agent i's row of it) where the family has a
    torch implementation, else through gymnasium (``batch_env``)."""
    offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
    if family is not None:
        return DeviceBlocks(family.copies(rows, counts), offsets)
    sizes = counts.tolist()
    return GymBlocks([batch_env(k, c) for k, c in zip(agents, sizes, strict=True)], device)
