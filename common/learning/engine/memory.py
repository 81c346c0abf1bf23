"""What a round of the engine holds on its device, where it peaks, and how many agents fit.

One local iteration of A agents holds, per copy-step (one step of one trajectory, counted to
the horizon H: the worst case, every episode running to its end):

- ``trajectories``: the recorded batch, observation, action, reward (float64) and whether the
  step happened, in buffers that double from 64 steps, so up to the next 64·2ʲ ≥ H;
- ``estimator``: the estimator's cells (each step's time and column, reward, alive and
  coefficient), kept through the gradient pass;
- ``gradient``: the gradient pass's alive steps cut into 64-step tiles (their indices, a copy
  of their observations and actions, their coefficients) and each tile's gradient (d floats
  per 64 steps);

plus, per copy, the sampler's state (keys, flags, the current observations, 32 steps of
decision draws and of its environment's own draws), and a fixed workspace: the packed tiles
one autograd call differentiates at once, with their θ rows (:func:`packed_elements`). The
peak comes at the gradient pass, with the batch still held; while sampling, the record's last
doubling holds one and a half of its buffers.

:func:`plan_round` cuts a round's agents into consecutive chunks whose planned peak fits the
budget (:func:`memory_budget`: ``algo.memory_gib``, else 80% of a CUDA device's free memory,
2 GiB on the CPU); the group trains the chunks one after another. An agent's numbers never
depend on its company, so θ does not depend on the chunks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

GIB = 1 << 30
CPU_BUDGET = 2 * GIB
"""What a CPU engine plans for by default (a machine shared with other processes)."""
CUDA_SHARE = 0.8
"""The share of a CUDA device's free memory a round plans for by default (the allocator's
fragmentation and the CUDA context take the rest)."""
RECORD_START = 64
"""Steps of the sampler's first record buffers (they double from there: the plan and the
sampler read this one number)."""
TILE = 64
PER_COPY = 256
"""Bytes of the sampler's own state per copy, besides its observation and decision draws."""


def packed_elements(device: torch.device) -> int:
    """Elements (tiles × 64 steps × d) one autograd call of the gradient pass takes at once:
    a CPU's caches favour small calls, a GPU's launch overhead large ones."""
    return 1 << 24 if device.type == "cpu" else 1 << 27


def memory_budget(device: torch.device, memory_gib: float | None) -> int:
    """Bytes a round may plan for on ``device`` (``algo.memory_gib`` where given)."""
    if memory_gib is not None:
        return int(memory_gib * GIB)
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(CUDA_SHARE * free)
    return CPU_BUDGET


def _itemsize(space: gym.Space) -> int:
    """Bytes of one recorded observation or action of ``space`` (discrete: int64; a box: its
    own dtype, or float32 for the policy's samples)."""
    if isinstance(space, gym.spaces.Discrete):
        return 8
    shape = space.shape or ()
    dtype = np.dtype(space.dtype) if space.dtype is not None else np.dtype(np.float32)
    return int(np.prod(shape, dtype=np.int64)) * max(dtype.itemsize, 4)


NOISE_CHUNK = 32
"""Time steps of the policy's decision draws the sampler makes at once for every copy."""
ENV_CHUNK = 8
"""Time steps of the environments' own draws (float64, a torch family's) made at once: fewer
than the decisions', as each is twice their size and their hashing's temporaries are as
large (the peak of a host's sampler)."""


@dataclass(frozen=True)
class StepBytes:
    """Bytes per copy-step of each part a round holds (see the module docstring)."""

    trajectories: float
    estimator: float
    gradient: float
    per_copy: float
    workspace: float

    @classmethod
    def of(
        cls,
        observation_space: gym.Space,
        action_space: gym.Space,
        num_params: int,
        noise_size: int,
        device: torch.device,
        step_noise: int = 0,
    ) -> StepBytes:
        """``noise_size``: the policy's decision draws per step (float32); ``step_noise``: the
        environment's own (float64, a torch family's)."""
        obs, act = _itemsize(observation_space), _itemsize(action_space)
        return cls(
            trajectories=obs + act + 8 + 1,
            estimator=8 + 8 + 8 + 1 + 8,
            gradient=16 + 5 * 8 + 2 * 8 + obs + act + 2 * 8 + 4 * num_params / TILE,
            per_copy=PER_COPY + 2 * obs + NOISE_CHUNK * 4 * noise_size + ENV_CHUNK * 8 * step_noise,
            workspace=4 * packed_elements(device),
        )

    def recorded(self, horizon: int) -> int:
        """Steps the record's buffers reach for a horizon of H (64·2ʲ ≥ H)."""
        return RECORD_START * 2 ** max(0, math.ceil(math.log2(max(horizon, 1) / RECORD_START)))

    def parts(self, copies: int, horizon: int) -> dict[str, int]:
        """Bytes of each part for ``copies`` trajectories of up to ``horizon`` steps."""
        steps = copies * horizon
        return {
            "trajectories": int(self.trajectories * copies * self.recorded(horizon)),
            "estimator": int(self.estimator * steps),
            "gradient": int(self.gradient * steps),
            "sampler": int(self.per_copy * copies),
            "workspace": int(self.workspace),
        }

    def peak(self, copies: int, horizon: int) -> int:
        """The larger of the gradient pass (everything at once) and the sampler's last
        doubling (one and a half records, its own state)."""
        parts = self.parts(copies, horizon)
        sampling = parts["trajectories"] * 3 // 2 + parts["sampler"]
        return max(sum(parts.values()), sampling)


@dataclass(frozen=True)
class RoundPlan:
    """A round's agents in chunks that each fit the budget."""

    chunks: list[range]
    """Positions (in the round's agent order) of each chunk's agents."""
    peak_bytes: int
    """The largest chunk's planned peak."""
    budget_bytes: int
    parts: dict[str, int]
    """What the largest chunk's peak is made of, in bytes."""

    @property
    def per_chunk(self) -> int:
        return max((len(c) for c in self.chunks), default=0)

    def describe(self) -> str:
        mib = {name: value / 2**20 for name, value in self.parts.items()}
        return (
            f"{len(self.chunks)} chunk(s) of ≤ {self.per_chunk:,} agents, planned peak "
            f"{self.peak_bytes / 2**20:,.0f} MiB of {self.budget_bytes / 2**20:,.0f} MiB ("
            + ", ".join(f"{name} {value:,.0f}" for name, value in mib.items())
            + ")"
        )


def plan_round(
    copies: Sequence[int], horizons: Sequence[int], step: StepBytes, budget: int
) -> RoundPlan:
    """Consecutive chunks of agents (agent i: ``copies[i]`` trajectories at once, of up to
    ``horizons[i]`` steps) whose planned peak fits ``budget`` bytes; an agent too large alone
    is a chunk of its own (a plan cannot split it)."""
    if copies:  # the usual round: all of it fits, and so would every chunk of it (a peak
        # grows with copies and horizon), so the loop below would make one chunk
        total, widest = sum(copies), max(horizons)
        peak = step.peak(total, widest)
        if peak <= budget:
            return RoundPlan([range(len(copies))], peak, budget, step.parts(total, widest))
    chunks: list[range] = []
    start, held, longest = 0, 0, 0
    largest: tuple[int, int, int] = (0, 0, 0)  # (peak, copies, horizon) of the largest chunk

    def close(end: int) -> None:
        nonlocal largest
        chunks.append(range(start, end))
        peak = step.peak(held, longest)
        if peak > largest[0]:
            largest = (peak, held, longest)

    for i, (count, horizon) in enumerate(zip(copies, horizons, strict=True)):
        wider = max(longest, horizon)
        if i > start and step.peak(held + count, wider) > budget:
            close(i)
            start, held, wider = i, 0, horizon
        held, longest = held + count, wider
    if len(copies) > start:
        close(len(copies))
    _, held, longest = largest
    return RoundPlan(
        chunks=chunks,
        peak_bytes=largest[0],
        budget_bytes=budget,
        parts=step.parts(held, longest),
    )
