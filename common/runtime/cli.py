"""Entry-point plumbing: compose the Hydra config, validate it once, report user errors briefly.

Every check runs before anything is started or written: a single run, every point of a
``-m`` sweep, a resume (which starts from the run directory's ``config.json``). A user mistake
is one line on stderr and exit status 2.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from fedhpg.common.config import RunConfig
from fedhpg.common.config_error import ConfigError
from fedhpg.common.runtime import timeline
from fedhpg.common.settings.keys import unknown_key

logger = logging.getLogger(__name__)

CONFIG_MODULE = "fedhpg.conf"
CONFIG_NAME = "config"
SCHEMA_NAME = "run_schema"
EXIT_USAGE = 2
EXIT_RUN_ABORTED = 3
"""An agent whose server ended the run early: nothing a restart could mend."""
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%H:%M:%S"
HELP_FLAGS = ("-h", "--help")
VERSION_FLAGS = ("-V", "--version")
NO_RESUME = ("", "null", "none", "false")
"""``resume=`` values that mean no resume, in any case."""


def version_text(prog: str) -> str:
    """``PROG VERSION`` (``--version`` on every entry point), the installed package's version."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        number = version("fedhpg")
    except PackageNotFoundError:
        number = "0+unknown"
    return f"{prog} {number}\n"


def answer_version(prog: str, args: Sequence[str]) -> None:
    """Print the version and exit 0 when ``args`` ask for it (before anything is imported)."""
    if any(a in VERSION_FLAGS for a in args):
        sys.stdout.write(version_text(prog))
        sys.exit(0)


def register_schema() -> None:
    """Make ``RunConfig`` the schema that ``conf/config.yaml`` extends (Hydra ConfigStore), and
    register the resolver its ``hydra.run.dir`` names (the one run-directory convention)."""
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    from fedhpg.common.runtime.run_files import hydra_run_dir

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
    from fedhpg.common.components import validate_run
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
    from fedhpg.common.settings.keys import all_keys

    return any(k.startswith(f"{key}.") for k in all_keys())


def _closest_group(key: str, overrides: Sequence[str]) -> str | None:
    """The config group whose name is closest to a mistyped top-level ``key``, as
    ``GROUP=VALUE`` where the value is one of its options (``agent=demo4`` →
    ``agents=demo4``), else ``GROUP``; None if no group is close (inside
    :func:`hydra_context`)."""
    import difflib

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
    from fedhpg.common.settings.keys import FREE_DICTS

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


PRINTING_FLAGS = (
    "--hydra-help", "--cfg", "-c", "--info", "-i", "--shell-completion", "-sc",
)  # fmt: skip
"""Hydra's flags that print and exit: Hydra sets up its own logging for them."""
HYDRA_FLAGS = (
    "--hydra-help", "--cfg", "-c", "--resolve", "--package", "-p", "--run", "-r",
    "--multirun", "-m", "--shell-completion", "-sc", "--config-path", "-cp", "--config-name",
    "-cn", "--config-dir", "-cd", "--experimental-rerun", "--info", "-i",
)  # fmt: skip
"""Hydra's own command-line flags (fedhpg-run passes them on)."""


def unknown_flag(args: Sequence[str], known: Sequence[str] = HYDRA_FLAGS) -> ConfigError | None:
    for arg in args:
        if arg.startswith("-") and arg.split("=", 1)[0] not in known:
            return ConfigError(arg, "not an option; give key=value overrides (see --help)")
    return None


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


def compose(overrides: Sequence[str], *, resumable: bool = False, report: bool = True) -> RunConfig:
    """Compose ``conf/config.yaml`` with command-line overrides, without Hydra's run dirs.
    With ``resumable`` and a ``resume=`` override, start from the run's ``config.json``.
    ``report``: log what each config group named on the command line changed beyond its own
    section (:func:`preset_changes`)."""
    from fedhpg.common.runtime.resume import compose_resume, resume_value, settle_auto

    overrides = own_overrides(overrides)
    if resumable:
        overrides = settle_auto(overrides)
    with hydra_context():
        if resumable and resume_value(overrides) is not None:
            return compose_resume(overrides)
        return to_run_config(compose_cfg(with_algorithm_strategy(overrides)))


def report_presets(overrides: Sequence[str]) -> None:
    """Log what each config group named in ``overrides`` set outside its own section
    (:func:`preset_changes`): for entry points that start a run, once it passed its checks."""
    from fedhpg.common.runtime.resume import resume_value

    overrides = own_overrides(overrides)
    if resume_value(overrides) is not None:
        return  # a resume runs its own config.json
    with hydra_context():
        for line in preset_changes(with_algorithm_strategy(overrides)):
            logger.info("%s", line)


def _named(overrides: Sequence[str], key: str) -> bool:
    return any(o.split("=", 1)[0].lstrip("+~") == key for o in overrides)


def with_algorithm_strategy(overrides: Sequence[str]) -> list[str]:
    """The overrides, plus ``strategy=S`` when the composed algorithm names the one strategy
    its updates mean anything to (``Algorithm.strategy``: fedpgbr's) and the command line
    names no strategy: ``algo=fedpgbr`` brings its server also where an env preset picked
    another (inside :func:`hydra_context`)."""
    overrides = list(overrides)
    if _named(overrides, "strategy") or _named(overrides, "strategy.name"):
        return overrides
    try:
        cfg = compose_cfg(overrides)
        from fedhpg.common.algorithms import ALGORITHMS
        from fedhpg.common.registry import import_plugins

        import_plugins(list(cfg.plugins))
        wanted = ALGORITHMS.get(str(cfg.algo.name)).strategy
    except (ConfigError, ImportError, KeyError, ValueError):
        return overrides  # validation names what is wrong
    if wanted is None or wanted == cfg.strategy.name:
        return overrides
    from hydra.core.global_hydra import GlobalHydra

    groups = GlobalHydra.instance().config_loader().get_group_options("strategy")
    return [*overrides, f"strategy={wanted}" if wanted in groups else f"strategy.name={wanted}"]


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

    from fedhpg.common.settings.keys import flatten

    loader = GlobalHydra.instance().config_loader()
    group_names = {name for name in loader.list_groups("") if name != "hydra"}
    chosen = [o for o in overrides if "=" in o and o.split("=", 1)[0] in group_names]
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


def compose_sweep(overrides: Sequence[str]) -> list[RunConfig]:
    """Compose and validate every point of a sweep before any job starts; an error names the
    point (its swept values) that fails."""
    from fedhpg.common.runtime.resume import resume_value

    overrides = own_overrides(overrides)
    if resume_value(overrides) is not None:
        raise ConfigError("resume", "resume one run directory at a time, without -m")
    runs = []
    with hydra_context():
        points = sweep_points(overrides)
        values: dict[str, set[str]] = {}
        for point in points:
            for item in point:
                values.setdefault(item.split("=", 1)[0], set()).add(item)
        swept = {key for key, seen in values.items() if len(seen) > 1}
        for number, point in enumerate(points, 1):
            try:
                runs.append(to_run_config(compose_cfg(with_algorithm_strategy(point))))
            except ConfigError as error:
                where = " ".join(p for p in point if p.split("=", 1)[0] in swept)
                label = f"sweep point {number}/{len(points)}" + (f" ({where})" if where else "")
                raise ConfigError(f"{label}: {error.key}", str(error).split(": ", 1)[1]) from None
    return runs


def _override_key(error: BaseException, overrides: Sequence[str]) -> str:
    """The override a Hydra error is about, when its message names one."""
    text = str(error)
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if key and key in text:
            return key
    return "overrides"


# --- logging, threads, the entry ------------------------------------------------------------------


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is now, so a live progress bar (which redirects it)
    keeps log lines above itself."""

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        pass


def setup_logging(level: str | int | None = None) -> None:
    """The one log format of every entry point and forked child: ``time LEVEL logger: text``
    on stderr. (conf/config.yaml turns Hydra's own logging setup off.)"""
    level = level or os.environ.get("FEDHPG_LOG_LEVEL", "INFO")
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(LOG_FORMAT, datefmt=LOG_DATE_FORMAT))
    root.addHandler(handler)
    root.setLevel(level)
    timeline.configure()


def limit_threads() -> None:
    """One thread for torch/OMP: K agent processes share two cores, more threads thrash."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) or SIGTERM: the process ends with status 128 + the signal's number
    (130, 143), as a shell reports a process the signal ended."""

    def __init__(self, signum: int = 2) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def status(self) -> int:
        return 128 + self.signum


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise :class:`Interrupted` in the main thread
    (SIGINT too: a process started with it ignored, as a shell's background job is, would
    otherwise not stop on it); the handlers before are put back after."""
    import signal

    def interrupt(signum: int, _frame: object) -> None:
        raise Interrupted(signum)

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def fail(error: ConfigError) -> int:
    sys.stderr.write(f"error: {error}\n")
    return EXIT_USAGE


def run_entry(
    main: Callable[[RunConfig], int],
    argv: Sequence[str] | None = None,
    *,
    resumable: bool = False,
    presets: bool = False,
) -> int:
    """Compose, validate and run ``main``; user mistakes exit 2 with one line, never a trace.
    ``presets``: log what the config groups named on the command line changed."""
    args = list(sys.argv[1:] if argv is None else argv)
    prog = os.path.basename(sys.argv[0])
    if any(a in VERSION_FLAGS for a in args):
        sys.stdout.write(version_text(prog))
        return 0
    if any(a in HELP_FLAGS for a in args):
        from fedhpg.common.runtime.help import help_text

        sys.stdout.write(help_text(prog))
        return 0
    flag = unknown_flag(args, known=())
    if flag is not None:
        return fail(flag)
    setup_logging()
    try:
        run = compose(args, resumable=resumable)
        if presets:
            report_presets(args)
    except ConfigError as error:
        return fail(error)
    limit_threads()
    try:
        with stop_signals():
            return main(run)
    except ConfigError as error:
        return fail(error)
    except Interrupted as interrupted:
        sys.stderr.write("interrupted\n")
        return interrupted.status
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        return 130
