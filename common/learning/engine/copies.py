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

import numpy as np
import torch

from fedhpg.common.learning.randomness import seeds, uniforms64
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
    narrows: bool
    """Whether :meth:`keep` can drop copies (the sampler then steps only the tiles of copies
    that still run)."""

    def reset(self, keys: torch.Tensor) -> torch.Tensor:
        """Start an episode in every copy, the copies' keys ``keys`` [N]; their first
        observations, in order."""
        ...

    def step(
        self, actions: torch.Tensor, running: torch.Tensor, noise: torch.Tensor | None = None
    ) -> CopyStep:
        """One step of every copy from ``actions`` [N] (one per copy), ``running`` [N] the
        copies whose episode goes on, ``noise`` [N, step_noise] the environments' uniforms
        (None when none). The result has every copy's row; a copy that is not running may
        be stepped or not (its row is then any value): the sampler masks it out."""
        ...

    def keep(self, columns: torch.Tensor) -> None:
        """Step only the copies ``columns`` (increasing) from now on, renumbered 0 … m − 1 in
        order (where :attr:`narrows`)."""
        ...

    def close(self) -> None: ...


class DeviceBlocks:
    """Blocks over a family's torch copies: every copy is stepped at every step until
    :meth:`keep` drops some, so a step's shapes are the kept copies', whatever has ended
    since (no count, no index to wait for)."""

    narrows = True

    def __init__(self, copies: DeviceCopies, offsets: torch.Tensor) -> None:
        self.copies = copies
        self.offsets = offsets.to(copies.device)
        self.step_noise = int(copies.step_noise)

    def reset(self, keys: torch.Tensor) -> torch.Tensor:
        columns = torch.arange(len(keys), device=self.offsets.device)
        return self.copies.reset(columns, KeyedReset(keys))

    def step(
        self, actions: torch.Tensor, running: torch.Tensor, noise: torch.Tensor | None = None
    ) -> CopyStep:
        return self.copies.step(actions, None, noise)

    def keep(self, columns: torch.Tensor) -> None:
        self.copies.keep(columns)

    def close(self) -> None:
        pass


class GymBlocks:
    """Blocks over gymnasium batch environments, one per block, on the CPU. A step steps the
    blocks that still hold a running copy (a block whose copies have all ended is left
    alone: a gymnasium environment stepped past its episode's end would pay for steps, and
    autoresets, no one reads); the other blocks' rows repeat their last observation."""

    step_noise = 0  # gymnasium environments draw from their own generators
    narrows = False  # a gymnasium batch environment keeps all its copies

    def keep(self, columns: torch.Tensor) -> None:
        raise NotImplementedError("gymnasium's batch environments keep all their copies")

    def __init__(self, envs: Sequence[BatchEnv], device: torch.device) -> None:
        self.envs = list(envs)
        sizes = [env.num_envs for env in self.envs]
        self.starts = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)])
        self.offsets = torch.from_numpy(self.starts.copy()).to(device)
        self.device = device
        self.last: np.ndarray | None = None
        """Every copy's latest observation."""

    def reset(self, keys: torch.Tensor) -> torch.Tensor:
        """Each block seeded by its first copy's key."""
        block_seeds = seeds(keys, -1)
        parts = [
            np.asarray(env.reset(seed=block_seeds[int(start)]))
            for env, start in zip(self.envs, self.starts[:-1], strict=True)
        ]
        first = np.concatenate(parts)
        self.last = first.copy()
        return torch.from_numpy(first).to(self.device)

    def step(
        self, actions: torch.Tensor, running: torch.Tensor, noise: torch.Tensor | None = None
    ) -> CopyStep:
        assert self.last is not None, "reset every block first"
        chosen = actions.cpu().numpy()
        going = running.cpu().numpy()
        total = len(going)
        obs = self.last
        reward = np.zeros(total, dtype=np.float64)
        terminated = np.ones(total, dtype=bool)
        truncated = np.zeros(total, dtype=bool)
        success = np.zeros(total, dtype=bool)
        for b, env in enumerate(self.envs):
            start, end = int(self.starts[b]), int(self.starts[b + 1])
            if not going[start:end].any():
                continue
            part = env.step(chosen[start:end])
            obs[start:end] = part.obs
            reward[start:end] = part.reward
            terminated[start:end] = part.terminated
            truncated[start:end] = part.truncated
            success[start:end] = part.success
        self.last = obs.copy()

        def tensor(values: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(values).to(self.device)

        return CopyStep(
            obs=tensor(obs),
            reward=tensor(reward),
            terminated=tensor(terminated),
            truncated=tensor(truncated),
            success=tensor(success),
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
