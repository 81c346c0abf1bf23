"""Bounds on message fields, declared once beside each field as ``Annotated`` metadata.

``trajectories: Count`` reads as "an int in [0, 2⁴⁰]". The codec enforces every bound of every
field it decodes (and encodes), so a peer cannot send a number out of range, an endless string
or a huge map; :func:`record_problems` applies the same bounds to a record built in-process
(the in-process pool's updates), so both paths refuse the same values. Pure Python.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from collections.abc import Sized
from dataclasses import dataclass
from typing import Annotated, Any


@dataclass(frozen=True)
class Bound:
    """What a value may be beyond its type: a closed range, finiteness, a size."""

    low: float | None = None
    high: float | None = None
    finite: bool = False
    """Floats: no NaN or ±Inf."""
    max_len: int | None = None
    """Strings and bytes: characters / bytes; lists: items; maps: entries."""
    key_len: int | None = None
    """Maps: the longest key."""

    def problem(self, value: Any) -> str | None:
        """Why ``value`` (already of the field's type) is out of bounds, or None."""
        kind = type(value)
        if kind is bool:
            return None
        if kind is list:  # a column: its length is all there is to bound
            if self.max_len is not None and len(value) > self.max_len:
                return f"{len(value)} long, more than {self.max_len}"
            return None
        if kind is float or kind is int or isinstance(value, int | float):  # the hot path
            if self.finite and not math.isfinite(value):
                return f"{value!r} is not finite"
            if self.low is not None and not value >= self.low:
                return f"{value!r} is below {self.low:g}"
            if self.high is not None and not value <= self.high:
                return f"{value!r} is above {self.high:g}"
            return None
        if self.max_len is not None and isinstance(value, Sized) and len(value) > self.max_len:
            return f"{len(value)} long, more than {self.max_len}"
        if self.key_len is not None and isinstance(value, dict):
            longest = max((len(key) for key in value), default=0)
            if longest > self.key_len:
                return f"a key of {longest} characters, more than {self.key_len}"
        return None


MAX_HOST_AGENTS = 1 << 16
"""Most logical agents one host serves (and one server request names)."""
MAX_BATCH_ANSWERS = 256
"""Most agents' answers in one message: a host sends a round's answers in ceil(A / this)
messages (fewer agents per message where θ is large)."""
MAX_COUNT = 2**40
"""Trajectories, steps, episodes: far above any real round, far below float32 trouble."""
MAX_SECONDS = 1e9
MAX_ROUND = 2**31 - 1

Count = Annotated[int, Bound(low=0, high=MAX_COUNT)]
Round = Annotated[int, Bound(low=0, high=MAX_ROUND)]
AgentIndex = Annotated[int, Bound(low=0, high=MAX_ROUND)]
Seconds = Annotated[float, Bound(low=0.0, high=MAX_SECONDS, finite=True)]
Finite = Annotated[float, Bound(finite=True)]
Fraction = Annotated[float, Bound(low=0.0, high=1.0, finite=True)]
Speed = Annotated[float, Bound(low=0.0, high=1e9, finite=True)]
Name = Annotated[str, Bound(max_len=128)]
"""Ids, codes, digests."""
Text = Annotated[str, Bound(max_len=4096)]
"""Human-readable reasons."""


def bounds_of(hint: Any) -> tuple[Any, tuple[Bound, ...]]:
    """(the plain type, its bounds) of a possibly ``Annotated`` hint; for an optional one
    (``Seconds | None``), those of its annotated arm."""
    if typing.get_origin(hint) in (types.UnionType, typing.Union):
        arms = [a for a in typing.get_args(hint) if typing.get_origin(a) is Annotated]
        if len(arms) == 1:
            return bounds_of(arms[0])
    if typing.get_origin(hint) is Annotated:
        base, *extras = typing.get_args(hint)
        return base, tuple(e for e in extras if isinstance(e, Bound))
    return hint, ()


@functools.cache
def _record_bounds(cls: type) -> tuple[tuple[str, tuple[Bound, ...], tuple[Bound, ...]], ...]:
    """(field, its bounds, its map items' bounds) per field of a record class, read once: the
    server checks every agent's stats every round, and ``get_type_hints`` is slow."""
    hints = typing.get_type_hints(cls, include_extras=True)
    layout = []
    for field in dataclasses.fields(cls):
        base, bounds = bounds_of(hints[field.name])
        item_bounds: tuple[Bound, ...] = ()
        if typing.get_origin(base) is dict:
            _, item_bounds = bounds_of(typing.get_args(base)[1])
        layout.append((field.name, bounds, item_bounds))
    return tuple(layout)


def record_problems(record: object) -> list[str]:
    """Every bound a dataclass instance breaks (top-level fields and the items of its maps)."""
    found = []
    record_type: Any = type(record)  # a class is hashable; mypy's type[object] is not
    for name, bounds, item_bounds in _record_bounds(record_type):
        value = getattr(record, name)
        for bound in bounds:
            if (problem := bound.problem(value)) is not None:
                found.append(f"{name}: {problem}")
        if item_bounds and isinstance(value, dict):
            for key, item in value.items():
                for bound in item_bounds:
                    if (problem := bound.problem(item)) is not None:
                        found.append(f"{name}[{key!r}]: {problem}")
    return found
