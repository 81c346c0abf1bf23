"""The checks every section's validation is made of: each raises a :class:`ConfigError`
naming the key and what it must be.
"""

from __future__ import annotations

import math
from typing import Any

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import Registry


def per_agent(values: list[Any], index: int) -> Any:
    """Agent ``index``'s entry of a per-agent list (one entry = every agent's)."""
    return values[0] if len(values) == 1 else values[index]


def require(condition: bool, key: str, message: str) -> None:
    if not condition:
        raise ConfigError(key, message)


def check_choice(value: str, key: str, allowed: tuple[str, ...] | Registry[Any]) -> None:
    """``value`` one of ``allowed``: a closed tuple, or an open vocabulary's names."""
    names = allowed.names() if isinstance(allowed, Registry) else allowed
    require(value in names, key, f"got {value!r}, allowed: {', '.join(names)}")


def check_number(value: Any, key: str, *, low: float, low_open: bool = False) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if low_open else value >= low)
    bound = f"> {low:g}" if low_open else f">= {low:g}"
    require(ok, key, f"got {value!r}, must be a finite number {bound}")


WIRE_INT_RANGE = (-(2**63), 2**63)
"""The integers a run's settings may hold: the wire carries signed 64-bit ones (the server
sends the config to every agent)."""


def check_wire_ints(value: Any, key: str) -> None:
    """Every integer in ``value`` (nested dicts and lists) within :data:`WIRE_INT_RANGE`."""
    if isinstance(value, dict):
        for name, item in value.items():
            check_wire_ints(item, f"{key}.{name}" if key else str(name))
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            check_wire_ints(item, f"{key}[{i}]")
    elif isinstance(value, int) and not isinstance(value, bool):
        low, end = WIRE_INT_RANGE
        require(
            low <= value < end,
            key,
            f"got {value}, beyond the signed 64-bit integers a run's settings travel as",
        )


def check_int(value: Any, key: str, *, low: int) -> None:
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low
    require(ok, key, f"got {value!r}, must be an integer >= {low}")


def check_agent_list(values: Any, key: str, num_agents: int) -> None:
    require(
        isinstance(values, list) and len(values) in (1, num_agents),
        key,
        f"needs 1 or num_agents={num_agents} values, got {values!r}",
    )
