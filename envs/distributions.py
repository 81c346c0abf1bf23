"""Seeded distributions written in a config: what a per-agent value is drawn from.

One spelling serves every per-agent draw of a run, a population's budgets and devices
(``agents.population.draw``) and a gymnasium environment's variation (``env.vary``):

- ``{choice: [8, 16, 32], weights: [3, 2, 1]}``: one of the values (weights optional, uniform
  by default);
- ``{uniform: {low: 0.0, high: 4e-4}}``;
- ``{lognormal: {median: 1.0, sigma: 0.5}}``;

each with optional ``min``/``max`` clipping (not of a choice's values). :func:`check` says what
is wrong with a spec, :func:`sample` draws one value from a generator the caller seeds (from
the run's seed, the agent's index and the field's name, so that agent k's value depends on
nothing else).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

KINDS = ("choice", "uniform", "lognormal")
EXTRAS = ("weights", "min", "max")


class DistributionError(ValueError):
    """A spec that is not a distribution; ``where`` is the part at fault (".weights", "")."""

    def __init__(self, where: str, message: str) -> None:
        super().__init__(message)
        self.where = where


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def kind_of(spec: Mapping[str, Any]) -> str:
    """The distribution's kind (one of :data:`KINDS`) of a checked spec."""
    return next(name for name in KINDS if name in spec)


def check(spec: Any, *, numbers_only: bool = True, kinds: tuple[str, ...] = KINDS) -> None:
    """Raise :class:`DistributionError` unless ``spec`` is one of ``kinds``. A choice may hold
    any plain values (strings, booleans) unless ``numbers_only``."""
    if not isinstance(spec, Mapping):
        raise DistributionError(
            "", f"got {spec!r}, must be a distribution, e.g. {{choice: [8, 16]}}"
        )
    named = [name for name in spec if name in kinds]
    extra = sorted(set(spec) - set(kinds) - set(EXTRAS))
    if len(named) != 1 or extra:
        raise DistributionError(
            "", f"needs exactly one of {', '.join(kinds)} (and weights, min, max)"
        )
    kind = named[0]
    if kind == "choice":
        values = spec["choice"]
        plain = _number if numbers_only else (lambda v: isinstance(v, int | float | str | bool))
        if not isinstance(values, list | tuple) or not values or not all(map(plain, values)):
            what = "number" if numbers_only else "value"
            raise DistributionError(".choice", f"got {values!r}, must be a non-empty {what} list")
        weights = spec.get("weights")
        if weights is not None and (
            not isinstance(weights, list | tuple)
            or len(weights) != len(values)
            or not all(_number(w) and w >= 0 for w in weights)
            or sum(weights) <= 0
        ):
            raise DistributionError(
                ".weights",
                f"got {weights!r}, must be {len(values)} numbers >= 0 with a positive sum",
            )
    elif kind in ("uniform", "lognormal"):
        if "weights" in spec:
            raise DistributionError(".weights", "only a choice takes weights")
        names = ("low", "high") if kind == "uniform" else ("median", "sigma")
        params = spec[kind]
        if not isinstance(params, Mapping) or set(params) != set(names):
            raise DistributionError(
                f".{kind}", f"got {params!r}, needs exactly {' and '.join(names)}"
            )
        for name in names:
            if not _number(params[name]):
                raise DistributionError(
                    f".{kind}.{name}", f"got {params[name]!r}, must be a number"
                )
        a, b = float(params[names[0]]), float(params[names[1]])
        if kind == "uniform" and not a <= b:
            raise DistributionError(".uniform", f"got low={a:g} > high={b:g}")
        if kind == "lognormal" and not (a > 0 and b >= 0):
            raise DistributionError(".lognormal", "median must be > 0 and sigma >= 0")
    for bound in ("min", "max"):
        if bound in spec and not _number(spec[bound]):
            raise DistributionError(f".{bound}", f"got {spec[bound]!r}, must be a number")
    if "min" in spec and "max" in spec and spec["min"] > spec["max"]:
        raise DistributionError(".min", f"got min={spec['min']:g} > max={spec['max']:g}")


def sample(spec: Mapping[str, Any], rng: np.random.Generator) -> Any:
    """One value of a checked spec, drawn from ``rng``."""
    if "choice" in spec:
        values = spec["choice"]
        weights = spec.get("weights")
        p = None if weights is None else np.asarray(weights, dtype=float) / float(sum(weights))
        return values[int(rng.choice(len(values), p=p))]
    if "uniform" in spec:
        value = float(rng.uniform(spec["uniform"]["low"], spec["uniform"]["high"]))
    else:
        params = spec["lognormal"]
        value = float(params["median"]) * math.exp(float(params["sigma"]) * rng.standard_normal())
    return min(max(value, float(spec.get("min", -math.inf))), float(spec.get("max", math.inf)))
