"""Shamir's secret sharing (1979) over GF(p), p = 2⁵²¹ − 1, for 32-byte secrets.

A secret s is the constant term of a random polynomial f of degree t − 1; share i is
(x_i, f(x_i)) for a non-zero x_i. Any t shares give s back by Lagrange interpolation at 0;
fewer reveal nothing about it (every value of s is equally consistent with them). The field is
prime and larger than any 32-byte secret, so a secret needs no splitting; coefficients come
from the operating system's entropy (``secrets``).
"""

from __future__ import annotations

import secrets
from collections.abc import Mapping, Sequence

PRIME = (1 << 521) - 1
"""A Mersenne prime above every 32-byte value."""
SHARE_BYTES = 66
"""A field element as bytes (⌈521 / 8⌉)."""
SECRET_BYTES = 32


def split(secret: bytes, xs: Sequence[int], threshold: int) -> list[bytes]:
    """The shares f(x) of ``secret`` at each of ``xs`` (distinct, in 1 .. p−1), any
    ``threshold`` of which recover it."""
    if len(secret) != SECRET_BYTES:
        raise ValueError(f"a secret is {SECRET_BYTES} bytes, got {len(secret)}")
    if not 1 <= threshold <= len(xs):
        raise ValueError(f"threshold {threshold} must be in 1 .. {len(xs)} (the shares)")
    if len(set(xs)) != len(xs) or not all(0 < x < PRIME for x in xs):
        raise ValueError("share points must be distinct and non-zero")
    coefficients = [int.from_bytes(secret, "big")]
    coefficients += [secrets.randbelow(PRIME) for _ in range(threshold - 1)]
    shares = []
    for x in xs:
        value = 0
        for coefficient in reversed(coefficients):  # Horner
            value = (value * x + coefficient) % PRIME
        shares.append(value.to_bytes(SHARE_BYTES, "big"))
    return shares


def combine(shares: Mapping[int, bytes], threshold: int) -> bytes:
    """The secret from at least ``threshold`` shares {x: f(x)} (the first ``threshold`` by x)."""
    if len(shares) < threshold:
        raise ValueError(f"{len(shares)} shares, fewer than the threshold {threshold}")
    points = sorted(shares.items())[:threshold]
    secret = 0
    for i, (x_i, share) in enumerate(points):
        numerator, denominator = 1, 1
        for j, (x_j, _) in enumerate(points):
            if i != j:
                numerator = numerator * x_j % PRIME
                denominator = denominator * (x_j - x_i) % PRIME
        y_i = int.from_bytes(share, "big")
        secret = (secret + y_i * numerator * pow(denominator, -1, PRIME)) % PRIME
    if secret >> (8 * SECRET_BYTES):
        raise ValueError("the shares do not interpolate to a 32-byte secret")
    return secret.to_bytes(SECRET_BYTES, "big")
