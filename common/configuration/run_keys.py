"""The config's keys: typos named with the nearest known key, every dotted key of the
schema, defaults filled in, and what a resumed run may not change.
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from typing import Any

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.run_roles import DIAGNOSTIC_KEYS, PLACEMENT_KEYS, groups

FREE_DICTS = (
    "env.options",
    "env.kwargs",
    "env.vary",
    "algo.params",
    "strategy.params",
    "agents.budget",
    "agents.population.draw",
)
"""Dicts whose keys belong to a registry entry (a family's options, an algorithm's ``Params``
and ``Budget``, a strategy's ``Params``): checked by their owners, not by this schema."""


def unknown_key(values: dict[str, Any], schema: type = RunConfig, prefix: str = "") -> str | None:
    """The first key of ``values`` that ``schema`` (a config dataclass) has no field for, as a
    one-line message with the nearest known key; None when every key is known. Hydra's ``+``
    adds keys beyond the schema, which OmegaConf would drop without a word."""
    fields = {f.name: f for f in dataclasses.fields(schema)}
    for name, value in values.items():
        key = f"{prefix}{name}"
        if name not in fields:
            close = difflib.get_close_matches(name, fields, n=1)
            if not close:  # a typo of a nested key, e.g. rounds → server.rounds_timeout_s
                close = difflib.get_close_matches(key, all_keys(), n=1)
            else:
                close = [f"{prefix}{close[0]}"]
            hint = f"; did you mean {close[0]}?" if close else ""
            return f"{key}: not a fedhpg key{hint}"
        nested = _nested_sections(schema).get(name)
        if nested is not None and isinstance(value, dict) and key not in FREE_DICTS:
            found = unknown_key(value, nested, f"{key}.")
            if found is not None:
                return found
    return None


def _nested_sections(schema: type) -> dict[str, type]:
    """The fields of ``schema`` that are config dataclasses themselves, by field name."""
    hints = typing.get_type_hints(schema)
    return {
        f.name: hints[f.name]
        for f in dataclasses.fields(schema)
        if isinstance(hints[f.name], type) and dataclasses.is_dataclass(hints[f.name])
    }


def all_keys(schema: type = RunConfig, prefix: str = "") -> list[str]:
    """Every dotted key of the schema (nested config dataclasses expanded)."""
    keys = []
    sections = _nested_sections(schema)
    for f in dataclasses.fields(schema):
        nested = sections.get(f.name)
        if nested is not None:
            keys.extend(all_keys(nested, f"{prefix}{f.name}."))
        else:
            keys.append(f"{prefix}{f.name}")
    return keys


def flatten(values: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted leaves of nested dicts: {"algo": {"step_size": 1}} → {"algo.step_size": 1}."""
    if not isinstance(values, dict) or (not values and prefix):
        return {prefix.rstrip("."): values}
    leaves: dict[str, Any] = {}
    for name, value in values.items():
        leaves.update(flatten(value, f"{prefix}{name}."))
    return leaves


def with_defaults(values: dict[str, Any]) -> dict[str, Any]:
    """A stored config (config.json, a checkpoint's copy) with every field the schema has
    now, so that a field added since it was written is not taken for a change."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.to_container(OmegaConf.merge(OmegaConf.structured(RunConfig), values))
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None) or "config"
        raise ConfigError(str(key), str(error).splitlines()[0]) from None
    assert isinstance(merged, dict)
    return {str(k): v for k, v in merged.items()}


def fixed_difference(run: dict[str, Any], invocation: dict[str, Any]) -> ConfigError | None:
    """The first key that a resume must keep (``GROUPS`` fixed) and this invocation changes,
    as an error naming the dotted key and both values; None when every fixed key is kept."""
    run = with_defaults(run)
    for group in groups("fixed"):
        before = flatten(run.get(group), f"{group}.")
        after = flatten(invocation.get(group), f"{group}.")
        for key in sorted((set(before) | set(after)) - {*PLACEMENT_KEYS, *DIAGNOSTIC_KEYS}):
            old, new = before.get(key, _UNSET), after.get(key, _UNSET)
            if old != new:
                return ConfigError(
                    key,
                    f"the run has {_show(old)}, this invocation {_show(new)}; a resume keeps "
                    f"{group} as it was",
                )
    return None


_UNSET = object()


def _show(value: Any) -> str:
    return "no such key" if value is _UNSET else repr(value)
