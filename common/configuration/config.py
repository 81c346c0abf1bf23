"""Typed run configuration, validated once at the entry points.

The dataclasses double as Hydra structured configs (see ``fedhpg.conf``). Inner code receives
these objects, never a DictConfig. :func:`validate` raises :class:`ConfigError` naming the key
and the allowed values; entry points turn it into a one-line message and exit status 2.

:class:`RunConfig` assembles the sections, one module each under
:mod:`fedhpg.common.configuration.settings` (each with its own validation); :func:`validate` runs
them in order. What each top-level key is for is
:data:`fedhpg.common.configuration.run_roles.GROUPS`; the keys themselves (typos, defaults, what a
resume may change) are :mod:`fedhpg.common.configuration.run_keys`.

This module is pure Python (no torch, zmq or gymnasium): every process imports it first, and
the checks that need a registry (algorithm, strategy, their options) live beside the registry
(:mod:`fedhpg.common.learning.components`, :mod:`fedhpg.server.strategies`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import import_plugins
from fedhpg.common.configuration.settings.agent import AgentConfig, validate_host_range
from fedhpg.common.configuration.settings.agents import AUTO, AgentsConfig, validate_agents
from fedhpg.common.configuration.settings.algo import AlgoConfig, validate_algo
from fedhpg.common.configuration.settings.attack import AttackConfig, validate_attack
from fedhpg.common.configuration.settings.checks import (
    check_choice,
    check_int,
    check_number,
    check_wire_ints,
    require,
)
from fedhpg.common.configuration.settings.cluster import ClusterConfig, validate_cluster
from fedhpg.common.configuration.settings.env import EnvConfig, validate_env
from fedhpg.common.configuration.settings.policy import LOG_STDS, EvalConfig, PolicyConfig
from fedhpg.common.configuration.settings.privacy import (
    PrivacyConfig,
    SecurityConfig,
    validate_privacy,
)
from fedhpg.common.configuration.settings.server import (
    CheckpointConfig,
    ServerConfig,
    validate_server,
)
from fedhpg.common.configuration.settings.strategy import (
    StrategyConfig,
    validate_participation,
    validate_tolerance,
)
from fedhpg.common.records.limits import MAX_HOST_AGENTS


@dataclass(kw_only=True)
class RunConfig:
    """One federated run."""

    seed: int = 0
    """Run seed: every agent's randomness derives from (seed, agent index, round, purpose)."""
    rounds: int = 50
    """T, the number of communication rounds."""
    plugins: list[str] = field(default_factory=list)
    """Modules to import first: they register algorithms, strategies or env families."""
    env: EnvConfig = field(default_factory=EnvConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    strategy: StrategyConfig = field(default_factory=StrategyConfig)
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    attack: AttackConfig = field(default_factory=AttackConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    server: ServerConfig = field(default_factory=ServerConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    privacy: PrivacyConfig = field(default_factory=PrivacyConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    resume: str | None = None
    """Continue a killed run: 'true' resumes ``server.out_dir``; a path resumes that run
    directory (``fedhpg-run resume=DIR``); 'auto' resumes ``server.out_dir`` if it holds a run
    and starts one otherwise (a server its supervisor restarts with the same command)."""


def validate(config: RunConfig) -> RunConfig:
    """Check every value this module can judge; raise :class:`ConfigError` naming the first bad
    key. The ``plugins`` are imported first, so the names they register in the vocabularies
    (:mod:`fedhpg.common.configuration.vocabularies`) are known. (Names and options of the algorithm
    and strategy registries: :func:`fedhpg.common.learning.components.validate_run`.)"""
    check_wire_ints(to_dict(config), "")
    check_int(config.seed, "seed", low=0)
    check_int(config.rounds, "rounds", low=1)
    for i, module in enumerate(config.plugins):
        require(
            isinstance(module, str) and bool(module.strip()),
            f"plugins[{i}]",
            f"got {module!r}, must be a module name",
        )
    # before the names they may register (attacks, clocks, round policies, ...) are checked
    import_plugins(list(config.plugins))
    validate_env(config.env)
    validate_algo(config.algo)
    validate_agents(config.agents)
    validate_attack(config.attack, config.agents.num_agents)
    validate_participation(config.strategy.participation, config.agents.num_agents)
    validate_tolerance(config.strategy, config.agents.num_agents)

    policy = config.policy
    require(
        isinstance(policy.hidden, list)
        and all(isinstance(h, int) and h >= 1 for h in policy.hidden),
        "policy.hidden",
        f"needs a list of positive layer widths, got {policy.hidden!r}",
    )
    check_choice(policy.log_std, "policy.log_std", LOG_STDS)
    require(
        isinstance(policy.name, str) and bool(policy.name.strip()),
        "policy.name",
        f"got {policy.name!r}, must be 'auto', a registered policy or package.module:Class",
    )

    check_int(config.eval.every, "eval.every", low=1)
    check_int(config.eval.episodes, "eval.episodes", low=1)
    if config.eval.horizon is not None:
        check_int(config.eval.horizon, "eval.horizon", low=1)
    if config.eval.stop_at is not None:
        stop_at = config.eval.stop_at
        require(
            isinstance(stop_at, int | float)
            and not isinstance(stop_at, bool)
            and math.isfinite(stop_at),
            "eval.stop_at",
            f"got {stop_at!r}, must be a finite return (or null: run every round)",
        )
    require(
        isinstance(config.checkpoint.keep_best, bool),
        "checkpoint.keep_best",
        f"got {config.checkpoint.keep_best!r}, must be true or false",
    )
    if config.checkpoint.every is not None:
        check_int(config.checkpoint.every, "checkpoint.every", low=1)

    validate_server(config.server, config.agents.num_agents)
    check_int(config.agent.index, "agent.index", low=0)
    validate_host_range(config.agent, config.agents.num_agents)
    if config.agents.per_host != AUTO:
        per_host = config.agents.per_host
        require(
            isinstance(per_host, int) and not isinstance(per_host, bool) and per_host >= 1,
            "agents.per_host",
            f"got {per_host!r}, must be 'auto' or an integer >= 1",
        )
        require(
            int(config.agents.per_host) <= MAX_HOST_AGENTS,
            "agents.per_host",
            f"got {config.agents.per_host}, more than the {MAX_HOST_AGENTS} agents one host "
            "may serve",
        )
    check_number(config.agent.connect_timeout_s, "agent.connect_timeout_s", low=0.0, low_open=True)
    check_int(config.agent.max_restarts, "agent.max_restarts", low=0)
    require(
        isinstance(config.security.curve, bool),
        "security.curve",
        f"got {config.security.curve!r}, must be true or false",
    )
    validate_privacy(config.privacy)
    validate_cluster(config.cluster)
    return config


def attacking_agents(run: RunConfig) -> list[int]:
    """The indices of the agents that attack (``attack.agents`` when ``attack.kind`` is set),
    in index order: what the log, the final table and metrics.jsonl mark."""
    if run.attack.kind == "none":
        return []
    return sorted({k for k in run.attack.agents if 0 <= k < run.agents.num_agents})


def to_dict(config: RunConfig) -> dict[str, Any]:
    """Plain dict of the config (msgpack- and JSON-friendly)."""
    return dataclasses.asdict(config)


def from_dict(values: dict[str, Any]) -> RunConfig:
    """Rebuild a typed RunConfig from plain values, checking keys and types (OmegaConf)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.merge(OmegaConf.structured(RunConfig), values)
        config = OmegaConf.to_object(merged)
    except OmegaConfBaseException as error:
        key = getattr(error, "full_key", None) or "config"
        raise ConfigError(str(key), str(error).splitlines()[0]) from None
    assert isinstance(config, RunConfig)
    return validate(config)
