"""Entry-point plumbing: the flags every entry point answers (``--help``, ``--version``), the
one-line refusal of a user mistake (exit status 2, never a traceback), logging, threads and
signals, and :func:`compose` of a run, a sweep or a resume.

Every check runs before anything is started or written: a single run, every point of a
``-m`` sweep, a resume (which starts from the run directory's ``config.json``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.runtime import timeline
from fedhpg.common.runtime.composition import (
    compose_run_cfg,
    group_choices,
    hydra_context,
    named,
    own_overrides,
    preset_changes,
    sweep_points,
    to_run_config,
    with_algorithm_strategy,
)
from fedhpg.common.runtime.composition import (
    validate_config as validate_config,  # the check of a config object (the Python API's)
)
from fedhpg.common.runtime.help import help_text
from fedhpg.common.runtime.resume import compose_resume, resume_value, settle_auto

logger = logging.getLogger(__name__)

EXIT_USAGE = 2
EXIT_RUN_ABORTED = 3
"""An agent whose server ended the run early: nothing a restart could mend."""
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%H:%M:%S"
HELP_FLAGS = ("-h", "--help")
VERSION_FLAGS = ("-V", "--version")


def version_text(prog: str) -> str:
    """``PROG VERSION`` (``--version`` on every entry point), the installed package's version."""
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


def repeated_key(args: Sequence[str]) -> ConfigError | None:
    """A key (or config group) that ``args``, a command line as its user typed it, sets twice
    to different values; Hydra would take the last one without a word. The same value twice is
    no conflict (nothing is lost: a suggested ``resume=true server.out_dir=DIR`` added to the
    command that made the run repeats its directory). Entry points ask this of their own argv
    only, before they add overrides of their own; a program's list of overrides (the Python
    API's, :func:`compose`'s) keeps Hydra's rule: the last one wins."""
    seen: dict[str, str] = {}
    for arg in args:
        if arg.startswith(("-", "~")) or "=" not in arg:
            continue  # flags, their values, deletions
        key, value = arg.split("=", 1)
        key = key.lstrip("+")
        first = seen.setdefault(key, arg)
        if first.split("=", 1)[1] != value:
            return ConfigError(key, f"given twice ({first}, {arg}); give it once")
    return None


def compose(overrides: Sequence[str], *, resumable: bool = False, report: bool = True) -> RunConfig:
    """Compose ``conf/config.yaml`` with command-line overrides, without Hydra's run dirs.
    With ``resumable`` and a ``resume=`` override, start from the run's ``config.json``.
    ``report``: log what each config group named on the command line changed beyond its own
    section (:func:`~fedhpg.common.runtime.composition.preset_changes`)."""
    overrides = own_overrides(overrides)
    if resumable:
        overrides = settle_auto(overrides)
    with hydra_context():
        if resumable and resume_value(overrides) is not None:
            return compose_resume(overrides)
        return to_run_config(compose_run_cfg(overrides))


def report_presets(overrides: Sequence[str]) -> None:
    """Log what each config group named in ``overrides`` set outside its own section
    (:func:`~fedhpg.common.runtime.composition.preset_changes`): for entry points that start
    a run, once it passed its checks."""
    overrides = own_overrides(overrides)
    if resume_value(overrides) is not None:
        return  # a resume runs its own config.json
    with hydra_context():
        if not group_choices(overrides) and not named(overrides, "algo.name"):
            return  # no group chosen, and none the algorithm could add: nothing to report
        for line in preset_changes(with_algorithm_strategy(overrides)):
            logger.info("%s", line)


def compose_sweep(overrides: Sequence[str]) -> list[RunConfig]:
    """Compose and validate every point of a sweep before any job starts; an error names the
    point (its swept values) that fails."""
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
                runs.append(to_run_config(compose_run_cfg(point)))
            except ConfigError as error:
                where = " ".join(p for p in point if p.split("=", 1)[0] in swept)
                label = f"sweep point {number}/{len(points)}" + (f" ({where})" if where else "")
                raise ConfigError(f"{label}: {error.key}", str(error).split(": ", 1)[1]) from None
    return runs


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
        sys.stdout.write(help_text(prog))
        return 0
    flag = unknown_flag(args, known=()) or repeated_key(args)
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
