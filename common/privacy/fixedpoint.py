"""Real vectors as integers modulo 2⁶⁴, so that masked sums are exact.

A value x in [−R, R] is encoded as round(x·s) in two's complement, s a power of two chosen so
that the sum of n such values cannot leave the signed 64-bit range: n·R·s ≤ 2⁶². Sums of
encodings (numpy's uint64 arithmetic wraps modulo 2⁶⁴) are then exactly the encoding of the
sum of the rounded values, and decode back with the resolution 1/s (≈ n·R·2⁻⁶², 2·10⁻¹² for a
thousand agents at R = 10⁴).
"""

from __future__ import annotations

import math

import numpy as np

HEADROOM_BITS = 62
"""log2 of n·R·s: two bits below the signed range, for the rounding of every term."""


def scale_for(count: int, bound: float) -> float:
    """The largest power of two s with count·bound·s ≤ 2⁶²."""
    if count < 1 or not bound > 0:
        raise ValueError(f"need count >= 1 and bound > 0, got {count}, {bound}")
    return float(2.0 ** math.floor(HEADROOM_BITS - math.log2(count * bound)))


def encode(values: np.ndarray, scale: float, bound: float) -> np.ndarray:
    """``values`` clipped to [−bound, bound], times ``scale``, rounded: uint64 words."""
    clipped = np.clip(np.asarray(values, dtype=np.float64), -bound, bound)
    return np.rint(clipped * scale).astype(np.int64).view(np.uint64)


def decode(words: np.ndarray, scale: float) -> np.ndarray:
    """The real values of (sums of) encodings: the words as signed integers, over ``scale``."""
    return np.asarray(words, dtype=np.uint64).view(np.int64).astype(np.float64) / scale


def add(total: np.ndarray, words: np.ndarray) -> np.ndarray:
    """total + words modulo 2⁶⁴, in place."""
    np.add(total, words, out=total)
    return total


def subtract(total: np.ndarray, words: np.ndarray) -> np.ndarray:
    """total − words modulo 2⁶⁴, in place."""
    np.subtract(total, words, out=total)
    return total
