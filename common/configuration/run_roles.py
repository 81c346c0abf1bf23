"""What each top-level key is for (:data:`GROUPS`): whether the server dictates it to agents,
whether a resumed run must keep it, whether runs that differ in it are different experiments.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fedhpg.common.configuration.config import RunConfig, from_dict, to_dict
from fedhpg.common.configuration.config_error import ConfigError


@dataclass(frozen=True, kw_only=True)
class GroupRole:
    dictated: bool
    """The server sends it in every welcome and agents adopt it (never host-specific)."""
    fixed: bool
    """It defines the run: a resumed run must keep it."""
    compared: bool
    """Runs that differ in it are different experiments: plots group by it."""
    agreed: bool = False
    """Dictated, but an agent must already hold the same: it consents instead of adopting, so
    that no server can lower what protects an agent."""


GROUPS: dict[str, GroupRole] = {
    "seed": GroupRole(dictated=True, fixed=True, compared=False),  # seeds are replicates
    "rounds": GroupRole(dictated=True, fixed=False, compared=False),  # may grow on resume
    "plugins": GroupRole(dictated=False, fixed=False, compared=False),  # each host its own
    "env": GroupRole(dictated=False, fixed=True, compared=True),  # checked at registration
    "algo": GroupRole(dictated=True, fixed=True, compared=True),
    "strategy": GroupRole(dictated=False, fixed=True, compared=True),  # the server's alone
    "agents": GroupRole(dictated=False, fixed=True, compared=True),  # each host its profile
    "attack": GroupRole(dictated=False, fixed=True, compared=True),  # attackers decide
    "policy": GroupRole(dictated=True, fixed=True, compared=True),
    "eval": GroupRole(dictated=True, fixed=False, compared=True),
    "checkpoint": GroupRole(dictated=False, fixed=False, compared=False),  # the server's files
    "server": GroupRole(dictated=False, fixed=False, compared=False),
    "agent": GroupRole(dictated=False, fixed=False, compared=False),
    "security": GroupRole(dictated=False, fixed=False, compared=False),  # paths stay on host
    "privacy": GroupRole(dictated=True, fixed=True, compared=True, agreed=True),
    "cluster": GroupRole(dictated=False, fixed=False, compared=False),  # fedhpg-cluster's jobs
    "resume": GroupRole(dictated=False, fixed=False, compared=False),
}
REPLICATE_KEYS = ("seed", "env.seed")
"""Keys whose values are replicates of one experiment (plots average over them)."""
PLACEMENT_KEYS = ("agents.per_host", "algo.memory_gib")
"""Where agents run, not what they compute (θ̃ does not depend on it): a resume may change
it, and runs that differ only in it are one experiment."""
DIAGNOSTIC_KEYS = ("algo.bound_estimates",)
"""What a run measures besides θ̃ (which does not depend on it): as free as placement."""


def groups(flag: str) -> tuple[str, ...]:
    """The top-level keys whose role has ``flag`` ('dictated', 'fixed' or 'compared')."""
    return tuple(name for name, role in GROUPS.items() if getattr(role, flag))


def dictated_settings(config: RunConfig) -> dict[str, Any]:
    """What the server sends agents: the dictated keys only (so no host's paths leave it)."""
    values = to_dict(config)
    return {key: values[key] for key in groups("dictated")}


def adopt_settings(own: RunConfig, dictated: dict[str, Any]) -> RunConfig:
    """This host's config with the server's dictated keys in place of its own; ConfigError
    where the server's value of an agreed key (privacy) differs from this host's own."""
    unknown = sorted(set(dictated) - set(groups("dictated")))
    if unknown:
        raise ConfigError(unknown[0], "the server may not dictate this key")
    values = to_dict(own)
    for group in groups("agreed"):
        if group in dictated and (differs := _first_difference(values[group], dictated[group])):
            key, mine, theirs = differs
            raise ConfigError(
                f"{group}.{key}" if key else group,
                f"the server runs {theirs!r}, this agent was started with {mine!r}: an agent "
                f"keeps its own {group} settings; start it with the server's",
            )
    return from_dict({**values, **dictated})


def _first_difference(mine: Any, theirs: Any, path: str = "") -> tuple[str, Any, Any] | None:
    """The first key (dotted; a ``mode`` first) whose values differ between two nested dicts,
    and both values."""
    if isinstance(mine, dict) and isinstance(theirs, dict):
        for key in sorted(set(mine) | set(theirs), key=lambda k: (k != "mode", k)):
            found = _first_difference(
                mine.get(key), theirs.get(key), f"{path}.{key}" if path else key
            )
            if found is not None:
                return found
        return None
    return None if mine == theirs else (path, mine, theirs)
