"""A run directory owned by one server at a time, checked before anything in it is touched.

:meth:`RunDirectory.claim` takes an exclusive ``flock`` on ``<out_dir>/.lock`` (held until
:meth:`release`, dropped by the kernel if the server dies), refuses an ``out_dir`` that is a
file, one that another live server holds, and one that already holds a run unless the run is
being resumed. Every refusal is a :class:`~fedhpg.common.config.ConfigError` naming the
setting: the entry point prints one line and exits 2, and nothing has been written.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from fedhpg.common.config import ConfigError, RunConfig
from fedhpg.common.runtime.run_files import (
    METRICS_NAME,
    RUNS_ROOT,
    holds_run,
    new_run_path,
    run_label,
)

LOCK_NAME = ".lock"


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

    @classmethod
    def claim(cls, path: Path, *, resume: bool, key: str = "server.out_dir") -> RunDirectory:
        """Own ``path`` for this server, or raise ConfigError without having changed it."""
        if path.exists() and not path.is_dir():
            raise ConfigError(key, f"{path} is a file, not a directory")
        try:
            path.mkdir(parents=True, exist_ok=True)
            fd = os.open(path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise ConfigError(key, f"cannot use {path}: {error.strerror or error}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise ConfigError(
                key, f"{path} is in use by another fedhpg-server (pid {holder}); wait for it"
            ) from None
        directory = cls(path, fd)
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
            directory.release()
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
        if self._lock_fd >= 0:
            with contextlib.suppress(OSError):
                os.ftruncate(self._lock_fd, 0)
            os.close(self._lock_fd)  # closing drops the flock
            self._lock_fd = -1

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


def _check_creatable(path: Path, key: str) -> None:
    """ConfigError unless ``path`` (absent) can be made: its nearest existing ancestor is a
    directory that takes a new directory. The probe is an empty directory made there and
    removed at once (only a try tells what /proc, /sys or a read-only mount refuse, even to
    root)."""
    import tempfile

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
    """:meth:`RunDirectory.claim` for a block: released at its end, and a disk or descriptor
    failure inside it becomes one RunDirectoryError line."""
    run_dir = RunDirectory.claim(path, resume=resume, key=key)
    try:
        yield run_dir
    except OSError as error:
        raise RunDirectoryError(f"cannot write {path}: {error.strerror or error}") from None
    finally:
        run_dir.release()
