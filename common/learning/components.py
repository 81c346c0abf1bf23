"""What the names in a run's config resolve to on an agent's side: its algorithm (with its
options) and each agent's budget and device profile. Validation of those names lives here,
beside the registry; the server's strategy is resolved in :mod:`fedhpg.server.strategies`."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from gymnasium.error import DependencyNotInstalled

from fedhpg.common.configuration.config import RunConfig, validate
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import OptionError, import_plugins, parse_options
from fedhpg.common.configuration.settings.checks import per_agent
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.common.heterogeneity.population import (
    DEVICE_FIELDS,
    budget_domain,
    budget_overrides,
    device_value,
    fields_of,
    validate_population,
)
from fedhpg.common.heterogeneity.variants import variant_of
from fedhpg.common.learning.algorithms import ALGORITHMS, Algorithm
from fedhpg.common.learning.policies import check_spaces
from fedhpg.envs.registry import UnknownEnvFamilyError

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class AgentProfile:
    """One agent's resolved compute: its algorithm's budget and its device's base speed (the
    whole device model: :func:`fedhpg.common.heterogeneity.device.device_for`)."""

    budget: Any
    """The algorithm's ``Budget`` dataclass for this agent."""
    speed: float


def resolve_algorithm(run: RunConfig) -> tuple[Algorithm[Any, Any], Any]:
    """The run's algorithm and its parsed ``algo.params``."""
    algorithm = ALGORITHMS.get(run.algo.name)
    params = parse_options(algorithm.Params, run.algo.params, "algo.params")
    try:
        algorithm.check(run.algo, params)
    except OptionError as error:
        raise ConfigError(f"algo.params.{error.field}", str(error)) from None
    return algorithm, params


def _listed_budget(run: RunConfig, algorithm: Algorithm[Any, Any], index: int) -> dict[str, Any]:
    fields = algorithm.Budget.__dataclass_fields__
    return {
        name: per_agent(entries, index)
        for name, entries in run.agents.budget.items()
        if name in fields
    }


def agent_budget(run: RunConfig, algorithm: Algorithm[Any, Any], index: int) -> Any:
    """Agent ``index``'s budget: the population's value of each field the algorithm uses,
    else that field's ``agents.budget`` list entry."""
    values = _listed_budget(run, algorithm, index)
    values.update(budget_overrides(run, index, tuple(algorithm.Budget.__dataclass_fields__)))
    return parse_options(algorithm.Budget, values, "agents.budget")


def planned_budget(budget: Any, override: Mapping[str, int] | None) -> Any:
    """``budget`` with the fields of the server's plan for this round (``agents.plan``) put
    in; no override: ``budget`` itself. Raises ValueError for a field the budget lacks or a
    value its checks refuse, so a bad request fails the round, not the agent."""
    if not override:
        return budget
    known = {f.name for f in dataclasses.fields(budget)}
    unknown = sorted(set(override) - known)
    if unknown:
        raise ValueError(f"the round's budget names {unknown}, not fields of {sorted(known)}")
    try:
        return dataclasses.replace(budget, **override)
    except (TypeError, ValueError) as error:
        raise ValueError(f"the round's budget {dict(override)} is refused: {error}") from None


def agent_profile(run: RunConfig, index: int) -> AgentProfile:
    algorithm, _ = resolve_algorithm(run)
    return AgentProfile(
        budget=agent_budget(run, algorithm, index),
        speed=device_value(run, index, "speed"),
    )


def _check_budget_keys(run: RunConfig, algorithm: Algorithm[Any, Any]) -> None:
    """A key no registered algorithm knows is a typo; one of another algorithm is unused."""
    mine = set(algorithm.Budget.__dataclass_fields__)
    anyone = {name for _, other in ALGORITHMS for name in other.Budget.__dataclass_fields__}
    for name in run.agents.budget:
        if name not in anyone:
            raise ConfigError(
                f"agents.budget.{name}",
                f"no algorithm has this budget; {algorithm.name} takes: {', '.join(sorted(mine))}",
            )
        if name not in mine:
            logger.debug("agents.budget.%s is not used by %s", name, algorithm.name)
    for name in fields_of(run.agents.population):
        if name not in anyone and name not in DEVICE_FIELDS:
            known = sorted(anyone | set(DEVICE_FIELDS))
            raise ConfigError(
                f"agents.population.{'draw.' + name if run.agents.population.draw else 'trace'}",
                f"{name!r} is no budget or device field; known: {', '.join(known)}",
            )


def _check_population_budgets(run: RunConfig, algorithm: Algorithm[Any, Any]) -> None:
    """Every budget value the population can give, through the algorithm's own check (a
    choice of 0, a trace row with a non-positive batch)."""
    mine = algorithm.Budget.__dataclass_fields__
    for key, values in budget_domain(run):
        try:
            parse_options(algorithm.Budget, {n: v for n, v in values.items() if n in mine}, "b")
        except ConfigError as error:
            if run.agents.population.kind == "trace":  # name the row's cell
                key = f"{key}.{error.key.rsplit('.', 1)[-1]}"
            raise ConfigError(key, str(error).split(": ", 1)[-1]) from None


def validate_env_family(run: RunConfig) -> None:
    """``env.family`` and ``env.options``, checked by generating agent 0's variant through
    the family registry (whatever a family is: built in, a plugin's, a dotted path), and its
    environment built once, its spaces ones a built-in policy takes (with ``policy=auto``). A
    family without per-index variants makes (and caches) all K here."""
    try:
        # One environment built too: a family whose library is missing (MuJoCo, Box2D without
        # the envs extra) fails here in one line, not in a traceback once the run has started;
        # so do spaces no built-in policy takes.
        env = variant_of(run, 0).make_env()
        try:
            check_spaces(run.policy, env.observation_space, env.action_space)
        finally:
            env.close()
    except UnknownEnvFamilyError as error:
        raise ConfigError("env.family", str(error)) from None
    except (DependencyNotInstalled, ImportError) as error:
        raise ConfigError(
            "env.family",
            f"{run.env.family} cannot be built here: {str(error).splitlines()[0]} (the "
            "optional environments come with pip install 'fedhpg[envs]')",
        ) from None
    except (TypeError, ValueError) as error:
        key = getattr(error, "key", None) or ("env.options" if run.env.options else "env")
        raise ConfigError(key, str(error).splitlines()[0] if str(error) else repr(error)) from None


def _check_plan(run: RunConfig, algorithm: Algorithm[Any, Any]) -> None:
    """``agents.plan=theorem1`` plans FedHPG's B_k, τ_k from Theorem 1's estimated constants."""
    if run.agents.plan == "none":
        return
    if not algorithm.theorem1:
        raise ConfigError(
            "agents.plan",
            f"theorem1 plans Algorithm 1's batch_size and local_iters (fedhpg), not "
            f"{algorithm.name!r}'s: Theorem 1 does not hold for it",
        )
    if not run.algo.bound_estimates:
        raise ConfigError(
            "agents.plan",
            "theorem1 plans from Theorem 1's estimated constants: set algo.bound_estimates=true",
        )
    if ROUND_POLICIES.get(run.server.round_policy).asynchronous:
        # the planner prices wait-all rounds (a round lasts as long as its slowest agent)
        raise ConfigError(
            "agents.plan",
            "theorem1 plans synchronous rounds; server.round_policy=buffered has none to plan",
        )


def validate_run(run: RunConfig) -> RunConfig:
    """Everything an agent-side process can check: the config's values, the plugins, the
    environment family and its options, the algorithm, its options and every agent's budget.
    Raises ConfigError naming the key."""
    validate(run)
    validate_population(run.agents.population)
    import_plugins(run.plugins)
    validate_env_family(run)
    algorithm, _ = resolve_algorithm(run)
    if run.algo.bound_estimates and not algorithm.theorem1:
        raise ConfigError(
            "algo.bound_estimates",
            f"Theorem 1's constants are estimated for Algorithm 1 (fedhpg) only, not "
            f"{algorithm.name!r}",
        )
    if algorithm.strategy is not None and run.strategy.name != algorithm.strategy:
        raise ConfigError(
            "strategy",
            f"algo={algorithm.name} sends what only strategy={algorithm.strategy} aggregates, "
            f"got strategy={run.strategy.name}: add strategy={algorithm.strategy}",
        )
    _check_budget_keys(run, algorithm)
    _check_population_budgets(run, algorithm)
    _check_plan(run, algorithm)
    # Lists of one entry are every agent's: only the longest list's indices can differ.
    longest = max((len(entries) for entries in run.agents.budget.values()), default=1)
    for index in range(min(run.agents.num_agents, longest)):
        try:
            parse_options(algorithm.Budget, _listed_budget(run, algorithm, index), "agents.budget")
        except ConfigError as error:
            field = error.key.rsplit(".", 1)[-1]
            entries = run.agents.budget.get(field)
            key = f"agents.budget.{field}"
            if entries is not None:
                key += f"[{index if len(entries) > 1 else 0}]"
            raise ConfigError(key, str(error).split(": ", 1)[-1]) from None
    return run
