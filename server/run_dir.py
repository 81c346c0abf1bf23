"""A run directory owned by one server at a time, checked before anything in it is touched.

:meth:`RunDirectory.claim` takes an exclusive ``flock`` on ``<out_dir>/.lock`` (held until
:meth:`release`, dropped by the kernel if the server dies), refuses an ``out_dir`` that is a
file, one that another live server holds, and one that already holds a run unless the run is
being resumed. Every refusal is a :class:`~fedhpg.common.configuration.config_error.ConfigError`
naming the setting: the entry point prints one line and exits 2, and nothing has been written.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.runtime.cli import LOG_FORMAT
from fedhpg.common.runtime.run_files import (
    CONFIG_NAME,
    METRICS_NAME,
    PROGRESS_NAME,
    RUN_FILES,
    RUN_LOG_NAME,
    RUNS_ROOT,
    TENSORBOARD_DIR,
    WANDB_DIR,
    holds_run,
    new_run_path,
    run_label,
)

LOCK_NAME = ".lock"
RUN_LOG_DATE_FORMAT = "%Y-%m-%d %H:%M:%S"
"""run.log's times: with the date, as a run may span days and resumes."""


def written_names() -> frozenset[str]:
    """What a server writes in its run directory (beside ``.lock``): what
    :meth:`RunDirectory.discard` may remove."""
    return frozenset(
        {*RUN_FILES, CONFIG_NAME, RUN_LOG_NAME, PROGRESS_NAME, TENSORBOARD_DIR, WANDB_DIR}
    )


def new_run_dir(run: RunConfig, *, root: Path = RUNS_ROOT, now: float | None = None) -> Path:
    """A new run directory for ``run``: ``runs/<YYYYmmdd>-<HHMMSS>-<env>-<algo>``
    (:func:`~fedhpg.common.runtime.run_files.new_run_path`), as every entry point names one."""
    return new_run_path(run_label(run.env.family, run.env.id, run.algo.name), root=root, now=now)


class RunDirectoryError(RuntimeError):
    """The run directory cannot be written (disk full, descriptors exhausted, removed)."""


@dataclass
class RunDirectory:
    path: Path
    _lock_fd: int = -1
    made: list[Path] = field(default_factory=list)
    """The directories :meth:`claim` made (``path`` and missing parents), deepest first."""
    found: frozenset[str] = frozenset()
    """What ``path`` held when it was claimed: never removed by :meth:`discard`."""
    _made_lock: bool = False

    @classmethod
    def claim(cls, path: Path, *, resume: bool, key: str = "server.out_dir") -> RunDirectory:
        """Own ``path`` for this server, or raise ConfigError without having changed it."""
        if path.exists() and not path.is_dir():
            raise ConfigError(key, f"{path} is a file, not a directory")
        made = [d for d in (path, *path.parents) if not d.exists()]
        try:
            path.mkdir(parents=True, exist_ok=True)
            found = frozenset(os.listdir(path))
            fd = os.open(path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            cls(path, made=made, found=written_names()).discard()  # its directories alone
            raise ConfigError(key, f"cannot use {path}: {error.strerror or error}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            # the lock file may have been removed by its releasing owner after the open above
            replaced = os.fstat(fd).st_ino != os.stat(path / LOCK_NAME).st_ino
        except OSError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise ConfigError(
                key, f"{path} is in use by another fedhpg-server (pid {holder}); wait for it"
            ) from None
        if replaced:
            os.close(fd)
            raise ConfigError(key, f"{path} was taken by another fedhpg-server; wait for it")
        directory = cls(path, fd, made=made, found=found, _made_lock=LOCK_NAME not in found)
        try:
            if not resume and directory.holds_run():
                raise ConfigError(
                    key,
                    f"{path} holds a run already: continue it with resume=true, or choose an "
                    "empty directory",
                )
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            directory.discard()
            raise
        return directory

    @staticmethod
    def precheck(path: Path, *, resume: bool, key: str = "server.out_dir") -> None:
        """What :meth:`claim` would refuse, seen without changing anything (a file, a
        directory that cannot be made, a run already there): for entry points that check
        before they start."""
        try:
            exists = path.exists()
        except OSError as error:  # e.g. a parent this user may not search
            raise ConfigError(key, f"cannot use {path}: {error.strerror or error}") from None
        if exists and not path.is_dir():
            raise ConfigError(key, f"{path} is a file, not a directory")
        if not exists:
            _check_creatable(path, key)
        if not resume and holds_run(path):
            raise ConfigError(
                key,
                f"{path} holds a run already: continue it with resume=true, or choose an "
                "empty directory",
            )

    def holds_run(self) -> bool:
        return holds_run(self.path)

    def holds_rounds(self) -> bool:
        """Whether a round of the run was recorded: a line in metrics.jsonl, or anything in
        checkpoints/ (a checkpoint, even a corrupt one, or the privacy journal)."""
        try:
            if self.metrics.is_file() and self.metrics.read_bytes().strip():
                return True
            checkpoints = self.path / "checkpoints"
            return checkpoints.is_dir() and any(checkpoints.iterdir())
        except OSError:
            return True  # unreadable: treated as holding rounds, so nothing is overwritten

    def release(self) -> None:
        """Give the directory up: its ``.lock`` is removed if the claim made it (while still
        held, so no other server takes a lock on a removed file), else emptied."""
        if self._lock_fd >= 0:
            with contextlib.suppress(OSError):
                if self._made_lock:
                    os.unlink(self.path / LOCK_NAME)
                else:
                    os.ftruncate(self._lock_fd, 0)
            os.close(self._lock_fd)  # closing drops the flock
            self._lock_fd = -1

    def discard(self) -> None:
        """Release, and remove what this start made, for a start that failed before any round
        was recorded: the run files the server writes that were not there when it claimed
        the directory, then the directories the claim made, if that left them empty. What
        the directory held before, and anything else written into it, stays."""
        if self._lock_fd >= 0 and self.holds_rounds():
            self.release()
            return
        for name in sorted(written_names() - self.found):
            target = self.path / name
            with contextlib.suppress(OSError):
                if target.is_dir() and not target.is_symlink():
                    shutil.rmtree(target)
                elif target.exists():
                    target.unlink()
        self.release()
        for made in self.made:
            try:
                made.rmdir()
            except OSError:  # not empty (something else was written there), or gone
                break

    @property
    def metrics(self) -> Path:
        return self.path / METRICS_NAME

    def checked_metrics(self, rounds: int) -> list[str]:
        """The first ``rounds`` lines of metrics.jsonl, each the JSON record of its round;
        ConfigError naming the first line that is missing, torn or out of order."""
        try:
            lines = self.metrics.read_text(encoding="utf-8").splitlines()
        except FileNotFoundError:
            lines = []
        except (OSError, UnicodeDecodeError) as error:
            raise ConfigError("resume", f"cannot read {self.metrics}: {error}") from None
        for number in range(1, rounds + 1):
            problem = None
            if number > len(lines):
                problem = "is missing"
            else:
                try:
                    record = json.loads(lines[number - 1])
                except json.JSONDecodeError:
                    problem = "is not a JSON record (torn or overwritten)"
                else:
                    if not isinstance(record, dict) or record.get("round") != number:
                        problem = f"is not round {number}'s record (a gap or a foreign line)"
            if problem is not None:
                raise ConfigError(
                    "resume",
                    f"{self.metrics} line {number} {problem}; the checkpoint is of round "
                    f"{rounds}: restore the file, or start a new run",
                )
        return lines[:rounds]


@contextlib.contextmanager
def _run_log(path: Path) -> Iterator[None]:
    """This process's log lines at INFO and above also go to ``path`` (appended: a resumed run
    continues its log) while the block runs; what the other handlers show is unchanged."""
    root = logging.getLogger()
    handler = logging.FileHandler(path, encoding="utf-8", delay=True)  # made by its first line
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter(LOG_FORMAT, datefmt=RUN_LOG_DATE_FORMAT))
    before = root.level
    raised: list[tuple[logging.Handler, int]] = []
    if root.getEffectiveLevel() > logging.INFO:  # let INFO through to the file alone
        for other in root.handlers:
            if other.level < before:
                raised.append((other, other.level))
                other.setLevel(before)
        root.setLevel(logging.INFO)
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)
        handler.close()
        root.setLevel(before)
        for other, level in raised:
            other.setLevel(level)


def _check_creatable(path: Path, key: str) -> None:
    """ConfigError unless ``path`` (absent) can be made: its nearest existing ancestor is a
    directory that takes a new directory. The probe is an empty directory made there and
    removed at once (only a try tells what /proc, /sys or a read-only mount refuse, even to
    root)."""
    ancestor = next((parent for parent in path.parents if parent.exists()), None)
    if ancestor is None:  # the working directory itself was removed
        raise ConfigError(key, f"cannot create {path}: no such directory")
    if not ancestor.is_dir():
        raise ConfigError(key, f"cannot create {path}: {ancestor} is not a directory")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".fedhpg-probe-", dir=ancestor))
    except OSError as error:
        raise ConfigError(
            key,
            f"cannot create {path}: no directory can be made in {ancestor} "
            f"({error.strerror or error}); choose another {key}",
        ) from None


@contextlib.contextmanager
def claimed(path: Path, *, resume: bool, key: str = "server.out_dir") -> Iterator[RunDirectory]:
    """:meth:`RunDirectory.claim` for a block: released at its end, this process's log lines
    appended to its ``run.log`` meanwhile, and a disk or descriptor failure inside it becomes
    one RunDirectoryError line. A block that fails (not one that is
    interrupted: that run can be resumed) before a round was recorded leaves nothing of its
    own behind (:meth:`RunDirectory.discard`)."""
    run_dir = RunDirectory.claim(path, resume=resume, key=key)
    try:
        with _run_log(run_dir.path / RUN_LOG_NAME):
            yield run_dir
    except OSError as error:
        run_dir.discard()
        raise RunDirectoryError(f"cannot write {path}: {error.strerror or error}") from None
    except ConfigError:  # a refused resume of a run with rounds: nothing of the refusal stays
        if RUN_LOG_NAME not in run_dir.found:
            with contextlib.suppress(OSError):
                (run_dir.path / RUN_LOG_NAME).unlink(missing_ok=True)
        run_dir.discard()
        raise
    except Exception:
        run_dir.discard()
        raise
    finally:
        run_dir.release()
