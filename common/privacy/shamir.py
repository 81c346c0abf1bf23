"""Shamir's secret sharing (1979) over GF(p), p = 2⁵²¹ − 1, for 32-byte secrets.

A secret s is the constant term of a random polynomial f of degree t − 1; share i is
(x_i, f(x_i)) for a non-zero x_i. Any t shares give s back by Lagrange interpolation at 0;
fewer reveal nothing about it (every value of s is equally consistent with them). The field is
prime and larger than any 32-byte secret, so a secret needs no splitting; coefficients come
from the operating system's entropy (``secrets``).
"""

from __future__ import annotations

import functools
import secrets
from collections.abc import Callable, Mapping, Sequence

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
    points = sorted((x, _value(y)) for x, y in shares.items())[:threshold]
    return _secret(_at(points, 0))


class Inconsistent(ValueError):
    """Shares that no one polynomial of degree below the threshold goes through, without one
    share to blame: ``suspects`` are the points any one of which may be wrong."""

    def __init__(self, message: str, suspects: frozenset[int]) -> None:
        super().__init__(message)
        self.suspects = suspects


def rebuild(
    shares: Mapping[int, bytes],
    threshold: int,
    accept: Callable[[bytes], bool] | None = None,
) -> tuple[bytes, frozenset[int]]:
    """The secret of ``shares``, checked, and the points whose shares were found wrong.

    The first ``threshold`` points by x give the polynomial; every further share must lie on
    it, and the secret must fit 32 bytes and pass ``accept`` (where the caller can tell a right
    secret: a private key against its public key). Further shares that disagree while another
    agrees are the wrong ones; when none agrees, each share is left out in turn, and the one
    whose absence makes the rest agree (checkably) is. :class:`Inconsistent`, naming every
    share, when no one share explains the disagreement (one share more than the threshold: any
    of them may be the wrong one); ValueError for fewer than ``threshold`` shares. With exactly
    ``threshold`` shares and no ``accept`` nothing can be checked."""
    if len(shares) < threshold:
        raise ValueError(f"{len(shares)} shares, fewer than the threshold {threshold}")
    points = sorted((x, _value(y)) for x, y in shares.items())
    found = _checked(points, threshold, accept)
    if found is not None:
        return found
    blamed = []
    for x, _ in points:
        rest = [p for p in points if p[0] != x]
        if len(rest) > threshold or (len(rest) == threshold and accept is not None):
            again = _checked(rest, threshold, accept)
            if again is not None:
                blamed.append((again[0], again[1] | {x}))
    if len(blamed) == 1:
        return blamed[0]
    raise Inconsistent(
        f"{len(points)} shares do not interpolate to one secret", frozenset(x for x, _ in points)
    )


def _checked(
    points: list[tuple[int, int]], threshold: int, accept: Callable[[bytes], bool] | None
) -> tuple[bytes, frozenset[int]] | None:
    """The secret of ``points``' first ``threshold`` and the further points off its polynomial,
    if the secret passes and some further point (or ``accept``) vouches for it; else None.
    A secret ``accept`` vouches for is taken without reading the further points."""
    base, further = points[:threshold], points[threshold:]
    xs = tuple(x for x, _ in base)
    value = _at(base, 0)
    if value >> (8 * SECRET_BYTES):
        return None
    if accept is not None and accept(value.to_bytes(SECRET_BYTES, "big")):
        # the secret checks out on its own: further shares cannot change it, none is read
        return value.to_bytes(SECRET_BYTES, "big"), frozenset()
    off = frozenset(x for x, y in further if _at(base, x, xs) != y)
    if further and len(off) == len(further):
        return None
    secret = value.to_bytes(SECRET_BYTES, "big")
    if accept is not None and not accept(secret):
        return None
    return secret, off


def _value(share: bytes) -> int:
    value = int.from_bytes(share, "big")
    if len(share) != SHARE_BYTES or value >= PRIME:
        raise ValueError(f"a share is a field element of {SHARE_BYTES} bytes")
    return value


def _secret(value: int) -> bytes:
    if value >> (8 * SECRET_BYTES):
        raise ValueError("the shares do not interpolate to a 32-byte secret")
    return value.to_bytes(SECRET_BYTES, "big")


def _at(points: list[tuple[int, int]], at: int, xs: tuple[int, ...] | None = None) -> int:
    """The polynomial through ``points`` (distinct x) evaluated at ``at``: Σ y_i ℓ_i(at)."""
    xs = xs if xs is not None else tuple(x for x, _ in points)
    inverses = _inverse_denominators(xs)
    count = len(xs)
    before = [1] * (count + 1)  # ∏_{j<i} (at − x_j)
    for i, x in enumerate(xs):
        before[i + 1] = before[i] * (at - x) % PRIME
    total, after = 0, 1  # after: ∏_{j>i} (at − x_j)
    for i in range(count - 1, -1, -1):
        total = (total + points[i][1] * before[i] % PRIME * after % PRIME * inverses[i]) % PRIME
        after = after * (at - xs[i]) % PRIME
    return total


@functools.lru_cache(maxsize=64)
def _inverse_denominators(xs: tuple[int, ...]) -> tuple[int, ...]:
    """1 / ∏_{j≠i} (x_i − x_j) for each point of ``xs`` (the same for every secret whose
    shares come from the same holders)."""
    inverses = []
    for i, x_i in enumerate(xs):
        denominator = 1
        for j, x_j in enumerate(xs):
            if i != j:
                denominator = denominator * (x_i - x_j) % PRIME
        inverses.append(pow(denominator, -1, PRIME))
    return tuple(inverses)
