"""Composition of a run's config: ``conf/config.yaml`` with the command line's overrides
through Hydra, validated into a :class:`~fedhpg.common.configuration.config.RunConfig`, and Hydra's
and OmegaConf's errors turned into one :class:`~fedhpg.common.configuration.config.ConfigError`
naming the key.

The layer under the entry points (:mod:`.cli`), resuming (:mod:`.resume`) and ``--help``
(:mod:`.help`): it imports none of them. Hydra and OmegaConf are imported where they are used,
so that an entry point's ``--version`` and its refusal of a mistyped flag answer without them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
from collections.abc import Iterator, Sequence
from typing import Any

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import import_plugins
from fedhpg.common.configuration.run_keys import FREE_DICTS, all_keys, flatten, unknown_key
from fedhpg.common.runtime.run_files import hydra_run_dir

CONFIG_MODULE = "fedhpg.conf"
CONFIG_NAME = "config"
SCHEMA_NAME = "run_schema"
NO_RESUME = ("", "null", "none", "false")
"""``resume=`` values that mean no resume, in any case."""


def register_schema() -> None:
    """Make ``RunConfig`` the schema that ``conf/config.yaml`` extends (Hydra ConfigStore), and
    register the resolver its ``hydra.run.dir`` names (the one run-directory convention)."""
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    ConfigStore.instance().store(name=SCHEMA_NAME, node=RunConfig)
    if not OmegaConf.has_resolver("fedhpg_run_dir"):
        OmegaConf.register_new_resolver("fedhpg_run_dir", hydra_run_dir)


def to_run_config(cfg: object) -> RunConfig:
    """DictConfig → validated RunConfig; unknown keys and OmegaConf type errors become
    ConfigError."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    assert isinstance(cfg, DictConfig)
    try:
        values = OmegaConf.to_container(cfg, resolve=True)
        assert isinstance(values, dict)
        values.pop("hydra", None)
        typo = unknown_key({str(k): v for k, v in values.items()})
        if typo is not None:
            key, message = typo.split(": ", 1)
            raise ConfigError(key, message)
        config = OmegaConf.to_object(cfg)
    except OmegaConfBaseException as error:
        raise ConfigError(
            str(getattr(error, "full_key", "") or "config"), _first_line(error)
        ) from None
    if not isinstance(config, RunConfig):
        raise ConfigError("config", "the composed config is not a fedhpg run config")
    return validate_config(config)


def validate_config(config: RunConfig) -> RunConfig:
    """Every check a process can make of its own config: values, plugins, the environment
    family and its options, the algorithm and budgets, the key files it names. (The server
    also checks ``strategy``.)"""
    from fedhpg.common.learning.components import validate_run
    from fedhpg.common.wire.security import validate_security

    validate_run(config)
    validate_security(config.security)
    if isinstance(config.resume, str) and config.resume.strip().lower() in NO_RESUME:
        # Hydra reads resume=false as the boolean, which the str field turns into "False":
        # without this it named a run directory "False" and resumed it.
        config = dataclasses.replace(config, resume=None)
    return config


def _first_line(error: BaseException) -> str:
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__


def _one_line(error: BaseException) -> str:
    """Hydra puts the useful part ("could not be converted to Float") on later lines."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    noise = ("full_key", "object_type", "reference_type", "Set the")
    useful = [line for line in lines if not line.startswith(noise)]
    return "; ".join(useful[:2]) if useful else type(error).__name__


@contextlib.contextmanager
def hydra_context() -> Iterator[None]:
    """Hydra initialised on ``fedhpg.conf`` (no run directory, no logging set up)."""
    from hydra import initialize_config_module

    register_schema()
    with initialize_config_module(config_module=CONFIG_MODULE, version_base=None):
        yield


@contextlib.contextmanager
def hydra_errors(overrides: Sequence[str]) -> Iterator[None]:
    """Hydra's and OmegaConf's errors about overrides, as one ConfigError naming the key."""
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import OmegaConfBaseException

    try:
        yield
    except MissingConfigException as error:
        key = _override_key(error, overrides)
        options = getattr(error, "options", None) or []
        chosen = next((o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == key), "?")
        raise ConfigError(
            key, f"no such option {chosen!r}; allowed: {', '.join(options)}"
        ) from None
    except (HydraException, OmegaConfBaseException) as error:
        cause = error.__cause__ if isinstance(error.__cause__, OmegaConfBaseException) else error
        key = getattr(cause, "full_key", None) or _override_key(error, overrides)
        if "To append to your config use +" in str(error):
            typo = _typo(key)
            group = _closest_group(key, overrides)
            if typo is not None and group is not None:
                plain, _, hinted = typo.partition("; did you mean ")
                if hinted in ("", f"{group.split('=', 1)[0]}?"):  # no key nearer than the group
                    typo = f"{plain}; did you mean {group}?"
            if typo is not None:
                raise ConfigError(key, typo) from None
            raise ConfigError(
                key,
                f"not in the composed config; add it with +{key}=... (an algorithm's budget and "
                "options come with its group: algo=NAME)",
            ) from None
        if _is_section(key) and _value_of(key, overrides) is not None:
            group = _closest_group(key, overrides)
            hint = f"; did you mean {group}?" if group is not None else ""
            raise ConfigError(
                key, f"a section of settings ({key}.KEY=VALUE), not a config group{hint}"
            ) from None
        raise ConfigError(key, _one_line(cause)) from None


def _value_of(key: str, overrides: Sequence[str]) -> str | None:
    """The value the overrides give ``key`` (the last one), or None."""
    values = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0].lstrip("+~") == key]
    return values[-1] if values else None


def _is_section(key: str) -> bool:
    """Whether ``key`` names a section of settings (``agent``, ``agents.population``)."""
    return any(k.startswith(f"{key}.") for k in all_keys())


def _closest_group(key: str, overrides: Sequence[str]) -> str | None:
    """The config group whose name is closest to a mistyped top-level ``key``, as
    ``GROUP=VALUE`` where the value is one of its options (``agent=demo4`` →
    ``agents=demo4``), else ``GROUP``; None if no group is close (inside
    :func:`hydra_context`)."""
    from hydra.core.global_hydra import GlobalHydra

    if "." in key or not GlobalHydra.instance().is_initialized():
        return None
    loader = GlobalHydra.instance().config_loader()
    groups = [name for name in loader.list_groups("") if name not in ("hydra", key)]
    close = difflib.get_close_matches(key, groups, n=1, cutoff=0.75)
    if not close:
        return None
    value = _value_of(key, overrides)
    if value is not None and value in loader.get_group_options(close[0]):
        return f"{close[0]}={value}"
    return close[0]


def _typo(key: str) -> str | None:
    """Why ``key`` is no fedhpg key (with the nearest one), or None if it could be one."""
    if any(key.startswith(f"{free}.") for free in FREE_DICTS):
        return None
    nested: dict[str, object] = {}
    node = nested
    parts = key.split(".")
    for part in parts[:-1]:
        node[part] = node = {}
    node[parts[-1]] = None
    found = unknown_key(nested)
    return found.split(": ", 1)[1] if found is not None else None


def compose_cfg(overrides: Sequence[str]) -> Any:
    """The composed DictConfig (inside :func:`hydra_context`)."""
    from hydra import compose as hydra_compose

    with hydra_errors(overrides):
        return hydra_compose(config_name=CONFIG_NAME, overrides=list(overrides))


COMPOSING_HYDRA_KEYS = ("hydra.searchpath",)
"""Hydra settings that change what the config composes to (more config groups): kept with
the overrides a run is composed and checked with; every other ``hydra.*`` is Hydra's alone."""


def own_overrides(args: Sequence[str]) -> list[str]:
    """The config overrides among the arguments: no flags, no ``hydra.*`` settings other than
    :data:`COMPOSING_HYDRA_KEYS`."""
    return [
        a
        for a in args
        if not a.startswith("-")
        and (
            not a.lstrip("+~").startswith("hydra.")
            or a.lstrip("+~").split("=", 1)[0] in COMPOSING_HYDRA_KEYS
        )
    ]


def named(overrides: Sequence[str], key: str) -> bool:
    """Whether an override sets ``key`` (``key=...``, ``+key=...``, ``~key``)."""
    return any(o.split("=", 1)[0].lstrip("+~") == key for o in overrides)


def group_choices(overrides: Sequence[str]) -> list[str]:
    """The overrides that choose an option of a config group (``env=cartpole``), inside
    :func:`hydra_context`."""
    from hydra.core.global_hydra import GlobalHydra

    loader = GlobalHydra.instance().config_loader()
    group_names = {name for name in loader.list_groups("") if name != "hydra"}
    return [o for o in overrides if "=" in o and o.split("=", 1)[0] in group_names]


def algorithm_strategy(cfg: Any, overrides: Sequence[str]) -> str | None:
    """The override that adds ``strategy=S`` to ``overrides`` (composed as ``cfg``) when the
    composed algorithm names the one strategy its updates mean anything to
    (``Algorithm.strategy``: fedpgbr's) and the command line names no strategy: ``algo=fedpgbr``
    brings its server also where an env preset picked another. None where nothing is added
    (inside :func:`hydra_context`)."""
    if named(overrides, "strategy") or named(overrides, "strategy.name"):
        return None
    try:
        from fedhpg.common.learning.algorithms import ALGORITHMS

        import_plugins(list(cfg.plugins))
        wanted = ALGORITHMS.get(str(cfg.algo.name)).strategy
    except (ConfigError, ImportError, KeyError, ValueError):
        return None  # validation names what is wrong
    if wanted is None or wanted == cfg.strategy.name:
        return None
    from hydra.core.global_hydra import GlobalHydra

    groups = GlobalHydra.instance().config_loader().get_group_options("strategy")
    return f"strategy={wanted}" if wanted in groups else f"strategy.name={wanted}"


def with_algorithm_strategy(overrides: Sequence[str]) -> list[str]:
    """The overrides, plus the one :func:`algorithm_strategy` adds (inside
    :func:`hydra_context`)."""
    overrides = list(overrides)
    try:
        extra = algorithm_strategy(compose_cfg(overrides), overrides)
    except ConfigError:
        return overrides  # validation names what is wrong
    return overrides if extra is None else [*overrides, extra]


def compose_run_cfg(overrides: Sequence[str]) -> Any:
    """The composed DictConfig of :func:`with_algorithm_strategy`'s overrides, composed once
    where the algorithm adds no strategy (inside :func:`hydra_context`)."""
    overrides = list(overrides)
    cfg = compose_cfg(overrides)
    extra = algorithm_strategy(cfg, overrides)
    return cfg if extra is None else compose_cfg([*overrides, extra])


PRESET_SECTIONS = {
    "env": "env",
    "algo": "algo",
    "strategy": "strategy",
    "attack": "attack",
    "agents": "agents",
    "cluster": "cluster",
}
"""Config groups whose settings belong to a section of their own: what they set there is
their purpose, what they set elsewhere is reported (:func:`preset_changes`)."""


def preset_changes(overrides: Sequence[str]) -> list[str]:
    """For each config group named in ``overrides`` (``env=cartpole``), what choosing it
    changed outside its own section, against the same command line without it: one line each,
    e.g. ``env=cartpole also sets strategy=fedadam (was mean), algo.step_size=1.0 (was 0.5)``.
    Keys the command line sets itself are left out. (Inside :func:`hydra_context`.)"""
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    loader = GlobalHydra.instance().config_loader()
    group_names = {name for name in loader.list_groups("") if name != "hydra"}
    chosen = group_choices(overrides)
    if not chosen:
        return []
    explicit = {o.split("=", 1)[0].lstrip("+~") for o in overrides if o not in chosen}

    def composed(lines: list[str]) -> tuple[dict[str, Any], dict[str, str]]:
        from hydra import compose as hydra_compose

        with hydra_errors(lines):
            cfg = hydra_compose(config_name=CONFIG_NAME, overrides=lines, return_hydra_config=True)
        choices = {str(k): str(v) for k, v in cfg.hydra.runtime.choices.items()}
        values = OmegaConf.to_container(cfg)
        assert isinstance(values, dict)
        values.pop("hydra")
        return flatten(values), choices

    with_all, choices = composed(list(overrides))
    lines = []
    for choice in chosen:
        group = choice.split("=", 1)[0]
        try:
            without, choices_before = composed([o for o in overrides if o != choice])
        except ConfigError:  # the rest needs the group (a key only it declares): no baseline
            continue
        switched = {
            name: (choices[name], choices_before.get(name))
            for name in group_names
            if name != group and choices.get(name) != choices_before.get(name)
        }
        own = PRESET_SECTIONS.get(group)
        quiet = [s for s in (own, *switched) if s]
        changed = [
            f"{key}={_shown(with_all.get(key))} (was {_shown(without.get(key))})"
            for key in sorted(set(with_all) | set(without))
            if with_all.get(key) != without.get(key)
            and not any(key == s or key.startswith(f"{s}.") for s in quiet)
            and not any(key == e or key.startswith(f"{e}.") for e in explicit)
        ]
        parts = [f"{name}={now} (was {before})" for name, (now, before) in switched.items()]
        if parts or changed:
            lines.append(f"{choice} also sets " + ", ".join(parts + changed))
    return lines


def _shown(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def sweep_points(overrides: Sequence[str]) -> list[list[str]]:
    """The overrides of every job a ``-m`` sweep would run (Hydra's parser expands
    ``a=1,2``, ``range(…)``, ``glob(…)``; the basic sweeper's cartesian product)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    with hydra_errors(overrides):
        parser = OverridesParser.create(config_loader=GlobalHydra.instance().config_loader())
        batches = BasicSweeper.split_arguments(parser.parse_overrides(list(overrides)), None)
    return [list(point) for batch in batches for point in batch]


def _override_key(error: BaseException, overrides: Sequence[str]) -> str:
    """The override a Hydra error is about, when its message names one."""
    text = str(error)
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if key and key in text:
            return key
    return "overrides"
