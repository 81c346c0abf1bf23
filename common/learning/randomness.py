"""Counter-based randomness: every draw is a function of where it is used, not of what came before.

A draw is ``hash(key, counter)``, where the key names one trajectory of one agent
(:func:`trajectory_keys`: seed, agent, round, purpose, local iteration, trajectory) and the
counter names the draw inside it (time step × draws per step + draw). Nothing is carried from
one draw to the next, so an agent's trajectories and θ cannot depend on which agents share its
batch, its host or the shape of the batch, on the CPU or on a GPU: the same integer arithmetic
gives the same bits everywhere (two's-complement int64, products wrapping modulo 2⁶⁴).

The hash is SplitMix64's finaliser (Steele, Lea and Flood, 2014), a bijection of 64-bit words
with full avalanche: written with operators alone, so one definition serves torch tensors on
any device and numba-compiled scalar code (:func:`mix64` is plain Python arithmetic; right
shifts are masked, so they are logical on signed words). Uniforms take the top 24 bits
(float32, the engine's precision) or 53 bits (float64).
"""

from __future__ import annotations

from enum import IntEnum
from typing import TypeVar

import torch

Word = TypeVar("Word", int, torch.Tensor)

GOLDEN = -7046029254386353131
"""0x9E3779B97F4A7C15 as a signed 64-bit word: SplitMix64's increment."""
_M1 = -4658895280553007687
"""0xBF58476D1CE4E5B9, signed."""
_M2 = -7723592293110705685
"""0x94D049BB133111EB, signed."""
_LOW34, _LOW37, _LOW33 = (1 << 34) - 1, (1 << 37) - 1, (1 << 33) - 1
_TOP24, _TOP53 = (1 << 24) - 1, (1 << 53) - 1


class Purpose(IntEnum):
    """What a stream is for: streams of different purposes never share a key."""

    TRAIN = 0
    EVALUATE = 1
    ATTACK = 2
    RESET = 3
    SCHEDULE = 4
    SERVER = 5
    """The trajectories a server samples itself (FedPG-BR's inner loop)."""


def signed(value: int) -> int:
    """An integer modulo 2⁶⁴ as the signed 64-bit word torch and numba hold."""
    value &= (1 << 64) - 1
    return value - (1 << 64) if value >= 1 << 63 else value


def mix64(z: Word) -> Word:
    """SplitMix64's finaliser: a bijection of 64-bit words (int64 tensors or scalars)."""
    z = (z ^ ((z >> 30) & _LOW34)) * _M1
    z = (z ^ ((z >> 27) & _LOW37)) * _M2
    return z ^ ((z >> 31) & _LOW33)


def absorb(state: Word, value: Word) -> Word:
    """The key after taking in one more field (order matters: (a, b) ≠ (b, a))."""
    return mix64(state + GOLDEN + value * GOLDEN)


def key_of(*fields: int) -> int:
    """The key of a tuple of non-negative integers, as a Python int (a signed 64-bit word)."""
    state = 0
    for value in fields:
        state = signed(absorb(state, signed(value)))
    return state


def trajectory_keys(
    seed: int,
    agents: torch.Tensor,
    round_index: int,
    purpose: Purpose,
    iteration: int,
    trajectories: torch.Tensor,
    owner: torch.Tensor | None = None,
) -> torch.Tensor:
    """The key of trajectory ``trajectories[i]`` of agent ``agents[i]`` (int64 tensors of one
    shape) in local iteration ``iteration`` of round ``round_index``; with ``owner``, of agent
    ``agents[owner[i]]`` (the agents' part of the key is then hashed once per agent)."""
    state = agent_key(
        torch.full_like(agents, key_of(seed, int(purpose))),
        agents,
        torch.full_like(agents, signed(round_index)),
        torch.full_like(agents, signed(iteration)),
    )
    return absorb(state if owner is None else state[owner], trajectories)


def agent_key(base: Word, agent: Word, round_index: Word, iteration: Word) -> Word:
    """The key of one agent's local iteration in a round, from ``base`` (seed and purpose,
    :func:`key_of`); its trajectory t's key is ``absorb(agent_key(...), t)``. Operators
    alone, so numba compiles this same definition (``common/learning/batched/kernels.py``)."""
    return absorb(absorb(absorb(base, agent), round_index), iteration)


def words(keys: torch.Tensor, counters: torch.Tensor | int) -> torch.Tensor:
    """hash(key, counter): 64 random bits per (key, counter), broadcast."""
    if isinstance(counters, int):
        return mix64(keys + signed((counters + 1) * GOLDEN))
    return mix64(keys + (counters + 1) * GOLDEN)


def uniforms(keys: torch.Tensor, counters: torch.Tensor | int) -> torch.Tensor:
    """Uniforms in [0, 1) with 24 random bits (float32), one per (key, counter)."""
    return ((words(keys, counters) >> 40) & _TOP24).to(torch.float32) * (1.0 / (1 << 24))


def uniforms64(keys: torch.Tensor, counters: torch.Tensor | int) -> torch.Tensor:
    """Uniforms in [0, 1) with 53 random bits (float64)."""
    return ((words(keys, counters) >> 11) & _TOP53).to(torch.float64) * (1.0 / (1 << 53))


def normals(keys: torch.Tensor, counters: torch.Tensor | int) -> torch.Tensor:
    """Standard normal draws (float32) by inverting the CDF of a 53-bit uniform, kept off 0."""
    u = uniforms64(keys, counters).clamp_min(2.0**-54)
    return torch.special.ndtri(u).to(torch.float32)


def seeds(keys: torch.Tensor, counter: int = 0) -> list[int]:
    """Non-negative 63-bit integers (a gymnasium environment's ``reset(seed=...)``)."""
    return [int(w) & ((1 << 63) - 1) for w in words(keys, counter).tolist()]
