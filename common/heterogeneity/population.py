"""Populations: agent k's budget and device fields drawn from seeded distributions or read
from a trace file, one agent index at a time.

Nothing here builds a K-long list: agent k's draw of a field seeds its own generator from
(run seed, k, field) alone, so it is the same on every host and costs the same for k = 9 999
as for k = 0; a trace is read once per file and indexed by row. A field the population does
not set keeps its per-agent list (``agents.budget.*``, ``agents.speeds``, ...).
"""

from __future__ import annotations

import csv
import functools
import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.agents import PopulationConfig
from fedhpg.common.configuration.settings.checks import per_agent
from fedhpg.envs import distributions

KINDS = ("none", "drawn", "trace")

DEVICE_FIELDS: dict[str, tuple[str, bool]] = {
    "speed": ("speeds", True),
    "step_delay_s": ("step_delays_s", False),
    "latency_s": ("latencies_s", False),
    "step_cost_s": ("step_costs_s", False),
    "grad_cost_s": ("grad_costs_s", False),
    "bandwidth_mbps": ("bandwidths_mbps", False),
}
"""Device field → (its ``agents.*`` list, whether it must be > 0 rather than >= 0)."""

DISTRIBUTIONS = distributions.KINDS
_STREAM_TAG = 0x9F0B
"""Keeps the population's streams apart from the device model's (seed, index) stream."""


@dataclass(frozen=True)
class Trace:
    """A population trace: its fields (header minus ``agent``) and one row per agent."""

    fields: tuple[str, ...]
    rows: tuple[dict[str, int | float], ...]


# --- validation -----------------------------------------------------------------------------


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _check_distribution(spec: Any, key: str) -> None:
    try:
        distributions.check(spec)
    except distributions.DistributionError as error:
        raise ConfigError(f"{key}{error.where}", str(error)) from None


def _check_device_value(value: float, name: str, key: str) -> None:
    _, positive = DEVICE_FIELDS[name]
    if not (value > 0 if positive else value >= 0):
        raise ConfigError(key, f"got {value!r}, must be {'>' if positive else '>='} 0")


def _lowest(spec: Mapping[str, Any]) -> float:
    """The least value a distribution can give (to check a device field's sign once)."""
    if "choice" in spec:
        low = min(float(v) for v in spec["choice"])
    elif "uniform" in spec:
        low = float(spec["uniform"]["low"])
    else:
        low = math.ulp(0.0)  # a lognormal is > 0
    low = max(low, float(spec.get("min", -math.inf)))
    return min(low, float(spec.get("max", math.inf)))


def validate_population(population: PopulationConfig) -> None:
    """Check ``agents.population`` (the schema here; budget values against the algorithm in
    :func:`fedhpg.common.learning.components.validate_run`). Raises ConfigError naming the key."""
    key = "agents.population"
    if population.kind not in KINDS:
        raise ConfigError(f"{key}.kind", f"got {population.kind!r}, allowed: {', '.join(KINDS)}")
    if population.kind != "drawn" and population.draw:
        raise ConfigError(f"{key}.draw", "is read only with kind=drawn")
    if population.kind != "trace" and population.trace is not None:
        raise ConfigError(f"{key}.trace", "is read only with kind=trace")
    if population.kind == "drawn":
        if not population.draw:
            raise ConfigError(f"{key}.draw", "kind=drawn needs at least one field's distribution")
        for name, spec in population.draw.items():
            _check_distribution(spec, f"{key}.draw.{name}")
            if name in DEVICE_FIELDS:
                _check_device_value(_lowest(spec), name, f"{key}.draw.{name}")
            elif "choice" not in spec:
                raise ConfigError(
                    f"{key}.draw.{name}", "a budget field is a count: give a choice of values"
                )
    if population.kind == "trace":
        if not isinstance(population.trace, str) or not population.trace.strip():
            raise ConfigError(f"{key}.trace", "kind=trace needs trace, the path of a CSV")
        load_trace(population.trace)


def _cell(text: str, key: str) -> int | float:
    try:
        value: int | float = int(text)
    except ValueError:
        try:
            value = float(text)
        except ValueError:
            raise ConfigError(key, f"got {text!r}, must be a number") from None
    if not math.isfinite(value):
        raise ConfigError(key, f"got {text!r}, must be a finite number")
    return value


@functools.lru_cache(maxsize=8)
def _load_trace(path: str, mtime_ns: int) -> Trace:
    key = "agents.population.trace"
    with open(path, newline="", encoding="utf-8") as file:
        lines = [line for line in file if line.strip() and not line.lstrip().startswith("#")]
    reader = csv.reader(lines)
    header = [name.strip() for name in next(reader, [])]
    if not header or header[0] != "agent":
        raise ConfigError(key, f"{path}: the header must start with 'agent', got {header!r}")
    fields = tuple(header[1:])
    if len(set(fields)) != len(fields) or not fields:
        raise ConfigError(key, f"{path}: the header needs distinct fields after 'agent'")
    rows = []
    for i, cells in enumerate(reader):
        where = f"{key}: {path} row {i}"
        if len(cells) != len(header):
            raise ConfigError(where, f"has {len(cells)} cells, the header {len(header)}")
        if _cell(cells[0].strip(), f"{where}.agent") != i:
            raise ConfigError(f"{where}.agent", f"got {cells[0].strip()!r}, rows must be 0, 1, …")
        row = {
            name: _cell(text.strip(), f"{where}.{name}")
            for name, text in zip(fields, cells[1:], strict=True)
        }
        for name, value in row.items():
            if name in DEVICE_FIELDS:
                _check_device_value(float(value), name, f"{where}.{name}")
        rows.append(row)
    if not rows:
        raise ConfigError(key, f"{path}: no agent rows")
    return Trace(fields=fields, rows=tuple(rows))


def load_trace(path: str) -> Trace:
    """The trace at ``path`` (read once per file version). Raises ConfigError naming the key
    and, for a bad cell, the row."""
    try:
        mtime_ns = Path(path).stat().st_mtime_ns
    except OSError as error:
        raise ConfigError("agents.population.trace", f"{path}: {error.strerror}") from None
    return _load_trace(path, mtime_ns)


# --- per-agent values -------------------------------------------------------------------------


def fields_of(population: PopulationConfig) -> tuple[str, ...]:
    """The fields the population sets (empty for kind=none)."""
    if population.kind == "drawn":
        return tuple(population.draw)
    if population.kind == "trace" and population.trace:
        return load_trace(population.trace).fields
    return ()


def _draw(spec: Mapping[str, Any], seed: int, index: int, name: str) -> int | float:
    # crc32, not hash(): string hashing is salted per process, and every host must agree.
    sequence = np.random.SeedSequence([seed, _STREAM_TAG, index, zlib.crc32(name.encode())])
    value: int | float = distributions.sample(spec, np.random.default_rng(sequence))
    return value


def population_value(run: RunConfig, index: int, name: str) -> int | float | None:
    """Agent ``index``'s value of field ``name`` from the population; None if it sets none."""
    population = run.agents.population
    if population.kind == "drawn":
        spec = population.draw.get(name)
        return None if spec is None else _draw(spec, run.seed, index, name)
    if population.kind == "trace" and population.trace:
        trace = load_trace(population.trace)
        row = trace.rows[index % len(trace.rows)]  # agents beyond the file wrap around
        return row.get(name)
    return None


def device_value(run: RunConfig, index: int, name: str) -> float:
    """Agent ``index``'s device field ``name`` (``speed``, ``step_delay_s``, ...): the
    population's value, else its ``agents.*`` list entry."""
    value = population_value(run, index, name)
    if value is None:
        value = per_agent(getattr(run.agents, DEVICE_FIELDS[name][0]), index)
    return float(value)


def budget_overrides(run: RunConfig, index: int, names: tuple[str, ...]) -> dict[str, Any]:
    """The population's values of the budget fields ``names`` for agent ``index``."""
    values = {}
    for name in names:
        value = population_value(run, index, name)
        if value is not None:
            values[name] = value
    return values


def budget_domain(run: RunConfig) -> list[tuple[str, dict[str, Any]]]:
    """Every budget value the population can give, as (config key, {field: value}) pairs for
    the algorithm's check: each choice of a drawn field, each row of a trace (whose key then
    takes the bad field's name after it)."""
    population = run.agents.population
    key = "agents.population"
    if population.kind == "drawn":
        return [
            (f"{key}.draw.{name}.choice[{i}]", {name: value})
            for name, spec in population.draw.items()
            if name not in DEVICE_FIELDS
            for i, value in enumerate(spec["choice"])
        ]
    if population.kind == "trace" and population.trace:
        trace = load_trace(population.trace)
        return [
            (
                f"{key}.trace: {population.trace} row {i}",
                {n: v for n, v in row.items() if n not in DEVICE_FIELDS},
            )
            for i, row in enumerate(trace.rows)
        ]
    return []
