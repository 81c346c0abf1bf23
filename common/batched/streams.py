"""The agents' random streams inside compiled kernels: ``np.random.default_rng([seed, k,
round, purpose])`` (common/worker.py's ``random_stream``), reproduced bit for bit in numba.

A kernel that trains a thousand agents in one call cannot take a thousand numpy Generators
(passing one costs ~10 µs, creating one ~18 µs: 28 ms a round for a host of 1,000 agents).
So the kernel seeds and steps each agent's stream itself, from the same entropy, with the same
algorithms numpy uses: the SeedSequence hash of the entropy words into a pool of four 32-bit
words, four 64-bit words drawn from the pool to seed PCG64 (XSL-RR 128/64), and
``random()`` = the top 53 bits of the next output times 2⁻⁵³. A stream is four uint64 words
(state high, state low, increment high, increment low), so a round's streams are a [A, 4]
array that the kernels advance in place. tests/test_compiled_engine.py checks the draws
against numpy's Generator for many seeds, agents and rounds.

All arithmetic is on uint64/uint32 values with explicit casts: numba, like numpy, turns a
mix of signed and unsigned 64-bit integers into a float.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

U32 = np.uint64(0xFFFFFFFF)
# SeedSequence's hash constants (numpy.random.bit_generator)
INIT_A = np.uint64(0x43B0D7E5)
MULT_A = np.uint64(0x931E8875)
INIT_B = np.uint64(0x8B51F9DD)
MULT_B = np.uint64(0x58F38DED)
MIX_MULT_L = np.uint64(0xCA01F9DD)
MIX_MULT_R = np.uint64(0x4973F715)
POOL = 4
# PCG64's 128-bit LCG multiplier, high and low words
MULT_HIGH = np.uint64(2549297995355413924)
MULT_LOW = np.uint64(4865540595714422341)
TWO_POW_MINUS_53 = 1.0 / 9007199254740992.0


def entropy_words(values: Sequence[int]) -> np.ndarray:
    """numpy's uint32 words of a list of non-negative ints: each int little-endian in as many
    words as it needs (0 takes one), the lists concatenated."""
    words: list[int] = []
    for value in values:
        if value < 0:
            raise ValueError("stream entropy must be non-negative")
        words.append(value & 0xFFFFFFFF)
        value >>= 32
        while value > 0:
            words.append(value & 0xFFFFFFFF)
            value >>= 32
    return np.asarray(words, dtype=np.uint32)


@njit(cache=True)
def _hashmix(value: np.uint64, hash_const: np.ndarray) -> np.uint64:
    value = (value ^ hash_const[0]) & U32
    hash_const[0] = (hash_const[0] * MULT_A) & U32
    value = (value * hash_const[0]) & U32
    return value ^ (value >> np.uint64(16))


@njit(cache=True)
def _mix(x: np.uint64, y: np.uint64) -> np.uint64:
    result = (MIX_MULT_L * x - MIX_MULT_R * y) & U32
    return result ^ (result >> np.uint64(16))


@njit(cache=True)
def _mulhi(a: np.uint64, b: np.uint64) -> np.uint64:
    """The high 64 bits of the 128-bit product a·b."""
    a_lo, a_hi = a & U32, a >> np.uint64(32)
    b_lo, b_hi = b & U32, b >> np.uint64(32)
    lo_lo = a_lo * b_lo
    hi_lo = a_hi * b_lo
    lo_hi = a_lo * b_hi
    hi_hi = a_hi * b_hi
    cross = (lo_lo >> np.uint64(32)) + (hi_lo & U32) + lo_hi
    return hi_hi + (hi_lo >> np.uint64(32)) + (cross >> np.uint64(32))


@njit(cache=True)
def _step(stream: np.ndarray) -> None:
    """state = state · MULT + inc (mod 2¹²⁸), on the words [state_hi, state_lo, inc_hi, inc_lo]."""
    s_hi, s_lo = stream[0], stream[1]
    low = s_lo * MULT_LOW
    high = _mulhi(s_lo, MULT_LOW) + s_lo * MULT_HIGH + s_hi * MULT_LOW
    new_lo = low + stream[3]
    carry = np.uint64(1) if new_lo < low else np.uint64(0)
    stream[0] = high + stream[2] + carry
    stream[1] = new_lo


@njit(cache=True)
def next_uint64(stream: np.ndarray) -> np.uint64:
    """PCG64's next output (XSL-RR of the advanced state)."""
    _step(stream)
    s_hi, s_lo = stream[0], stream[1]
    value = s_hi ^ s_lo
    rot = s_hi >> np.uint64(58)
    return (value >> rot) | (value << ((np.uint64(64) - rot) & np.uint64(63)))


@njit(cache=True)
def next_double(stream: np.ndarray) -> float:
    """``Generator.random()``: uniform on [0, 1) with 53 random bits."""
    return float(next_uint64(stream) >> np.uint64(11)) * TWO_POW_MINUS_53


@njit(cache=True)
def seed_stream(words: np.ndarray, stream: np.ndarray) -> None:
    """``default_rng(entropy)`` into ``stream``: SeedSequence(words) → 4 uint64 → PCG64."""
    hash_const = np.empty(1, dtype=np.uint64)
    hash_const[0] = INIT_A
    pool = np.empty(POOL, dtype=np.uint64)
    for i in range(POOL):
        pool[i] = _hashmix(np.uint64(words[i]) if i < len(words) else np.uint64(0), hash_const)
    for src in range(POOL):
        for dst in range(POOL):
            if src != dst:
                pool[dst] = _mix(pool[dst], _hashmix(pool[src], hash_const))
    for src in range(POOL, len(words)):
        for dst in range(POOL):
            pool[dst] = _mix(pool[dst], _hashmix(np.uint64(words[src]), hash_const))
    # generate_state(4, uint64): eight 32-bit words, paired little-endian
    out = np.empty(8, dtype=np.uint64)
    mult = INIT_B
    for i in range(8):
        value = (pool[i % POOL] ^ mult) & U32
        mult = (mult * MULT_B) & U32
        value = (value * mult) & U32
        out[i] = value ^ (value >> np.uint64(16))
    seed_hi = out[0] | (out[1] << np.uint64(32))
    seed_lo = out[2] | (out[3] << np.uint64(32))
    inc_hi = out[4] | (out[5] << np.uint64(32))
    inc_lo = out[6] | (out[7] << np.uint64(32))
    # pcg_setseq_128_srandom_r: state 0, inc = (initseq << 1) | 1, step, state += seed, step
    stream[0] = np.uint64(0)
    stream[1] = np.uint64(0)
    stream[2] = (inc_hi << np.uint64(1)) | (inc_lo >> np.uint64(63))
    stream[3] = (inc_lo << np.uint64(1)) | np.uint64(1)
    _step(stream)
    low = stream[1] + seed_lo
    carry = np.uint64(1) if low < seed_lo else np.uint64(0)
    stream[0] = stream[0] + seed_hi + carry
    stream[1] = low
    _step(stream)


@njit(cache=True)
def _seed_rows(words: np.ndarray, streams: np.ndarray) -> None:
    for row in range(words.shape[0]):
        seed_stream(words[row], streams[row])


def agent_streams(seed: int, agents: Sequence[int], round_index: int, purpose: int) -> np.ndarray:
    """The streams ``random_stream(seed, k, round_index, purpose)`` of ``agents``, [A, 4]."""
    streams = np.empty((len(agents), 4), dtype=np.uint64)
    ids = np.asarray(agents, dtype=np.int64).reshape(-1)
    if len(ids) and (ids.min() < 0 or ids.max() > 0xFFFFFFFF):
        for row, k in enumerate(agents):  # an index past one word (or a bad one): one by one
            seed_stream(entropy_words([seed, int(k), round_index, purpose]), streams[row])
        return streams
    # every agent's entropy is the same words but its index's one: seeded in one call (a
    # Python call per agent cost ~3 µs, 1.5 ms a round for a host of 500)
    head, tail = entropy_words([seed]), entropy_words([round_index, purpose])
    words = np.empty((len(ids), len(head) + 1 + len(tail)), dtype=np.uint32)
    words[:, : len(head)] = head
    words[:, len(head)] = ids
    words[:, len(head) + 1 :] = tail
    _seed_rows(words, streams)
    return streams
