"""Per-round checkpoints: msgpack with raw array bytes and a checksum; atomic writes; no pickle.

A checkpoint holds everything a killed server needs to continue exactly: θ̃, the round, the
strategy's state (whatever :meth:`Strategy.state` returned, e.g. fedadam's moments), the run's
counters (``state``) and how many ``metrics.jsonl`` lines belong to it. There are no
random-number states to keep: every random stream of a run is derived from (seed, agent,
round, purpose) where it is used.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import numpy as np
import torch

from fedhpg.common.types import SavedState

logger = logging.getLogger(__name__)
T = TypeVar("T")

CHECKPOINT_FORMAT = "fedhpg-checkpoint"
CHECKPOINT_VERSION = 3
"""3: the strategy's state under ``strategy``; 2 kept the server optimizer's in ``state`` and
``server_optimizer.*`` arrays (read as the strategy's state)."""
READABLE_VERSIONS = (1, 2, 3)
KEEP_CHECKPOINTS = 2


class CheckpointError(ValueError):
    """A checkpoint file is missing, torn, corrupt or of another format."""


@dataclass(frozen=True, kw_only=True)
class Checkpoint:
    round: int
    theta: torch.Tensor
    config: dict[str, Any]
    metrics_lines: int
    state: dict[str, Any]
    """The run's counters (trajectories per agent, elapsed time)."""
    strategy: SavedState = field(default_factory=SavedState)
    """The server strategy's state."""
    version: int = CHECKPOINT_VERSION
    """The format version the file was written in."""
    schedule: SavedState | None = None
    """Buffered rounds: the in-flight updates and the emulated clock (server/buffered.py)."""


def _pack_array(array: np.ndarray) -> dict[str, Any]:
    return {"dtype": array.dtype.str, "shape": list(array.shape), "data": array.tobytes()}


def _unpack_array(packed: dict[str, Any]) -> np.ndarray:
    dtype = np.dtype(packed["dtype"])
    if dtype.kind not in "fiub":  # plain numbers only: an object dtype would mean pickle
        raise ValueError(f"array dtype {dtype} is not allowed")
    return np.frombuffer(packed["data"], dtype=dtype).reshape(packed["shape"]).copy()


def checkpoint_path(directory: Path, round_number: int) -> Path:
    return directory / f"round-{round_number:06d}.ckpt"


def _pack_state(state: SavedState) -> dict[str, Any]:
    return {
        "scalars": state.scalars,
        "arrays": {name: _pack_array(a) for name, a in state.arrays.items()},
    }


def _unpack_state(saved: dict[str, Any]) -> SavedState:
    return SavedState(
        scalars=dict(saved["scalars"]),
        arrays={name: _unpack_array(a) for name, a in saved["arrays"].items()},
    )


def _payload(checkpoint: Checkpoint) -> bytes:
    extra = {} if checkpoint.schedule is None else {"schedule": _pack_state(checkpoint.schedule)}
    return msgpack.packb(
        {
            **extra,
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "round": checkpoint.round,
            "theta": _pack_array(checkpoint.theta.detach().cpu().numpy()),
            "config": checkpoint.config,
            "metrics_lines": checkpoint.metrics_lines,
            "state": checkpoint.state,
            "strategy": _pack_state(checkpoint.strategy),
        },
        use_bin_type=True,
    )


FD_RETRIES = 20
"""Tries of an open that failed for want of descriptors (EMFILE), 50 ms apart: the server's
connection guard frees descriptors within that time."""


def _open_retrying(opener: Callable[[], T]) -> T:
    for attempt in range(FD_RETRIES):
        try:
            return opener()
        except OSError as error:
            if error.errno not in (errno.EMFILE, errno.ENFILE) or attempt == FD_RETRIES - 1:
                raise
            time.sleep(0.05)
    raise AssertionError("unreachable")


def write_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary file, fsync, then rename over ``path``: readers see old or new.

    On any failure (a full disk, no descriptors) the temporary file is removed and ``path`` is
    as it was; the OSError propagates."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with _open_retrying(lambda: tmp.open("wb")) as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    directory = _open_retrying(lambda: os.open(path.parent, os.O_RDONLY))
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def save_checkpoint(directory: Path, checkpoint: Checkpoint) -> Path:
    """Write this round's checkpoint atomically and prune all but the newest few."""
    directory.mkdir(parents=True, exist_ok=True)
    body = _payload(checkpoint)
    path = checkpoint_path(directory, checkpoint.round)
    write_atomic(path, hashlib.sha256(body).digest() + body)
    for old in sorted(directory.glob("round-*.ckpt"))[:-KEEP_CHECKPOINTS]:
        old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path) -> Checkpoint:
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise CheckpointError(f"{path}: cannot read ({error.strerror})") from None
    digest, body = raw[:32], raw[32:]
    if len(raw) < 32 or hashlib.sha256(body).digest() != digest:
        raise CheckpointError(f"{path}: checksum mismatch (torn or corrupt file)")
    try:
        values = msgpack.unpackb(body, raw=False, strict_map_key=True)
        if (
            values.get("format") != CHECKPOINT_FORMAT
            or values.get("version") not in READABLE_VERSIONS
        ):
            raise CheckpointError(
                f"{path}: not a {CHECKPOINT_FORMAT} file of a readable version {READABLE_VERSIONS}"
            )
        version = int(values["version"])
        state = dict(values.get("state", {}))
        if version >= 3:
            strategy = _unpack_state(values["strategy"])
        else:  # v2: the server optimizer (today's fedadam) kept its state beside the counters
            prefix = "server_optimizer."
            strategy = SavedState(
                scalars=dict(state.pop("server_optimizer", {})),
                arrays={
                    name[len(prefix) :]: _unpack_array(a)
                    for name, a in values.get("arrays", {}).items()
                    if name.startswith(prefix)
                },
            )
        theta = _unpack_array(values["theta"])
        if theta.dtype != np.float32 or theta.ndim != 1 or not np.isfinite(theta).all():
            raise CheckpointError(f"{path}: θ̃ is not a finite float32 vector")
        return Checkpoint(
            round=int(values["round"]),
            theta=torch.from_numpy(theta),
            config=values["config"],
            metrics_lines=int(values["metrics_lines"]),
            state=state,
            strategy=strategy,
            version=version,
            schedule=_unpack_state(values["schedule"]) if "schedule" in values else None,
        )
    except (KeyError, TypeError, ValueError, AttributeError, msgpack.UnpackException) as error:
        if isinstance(error, CheckpointError):
            raise
        raise CheckpointError(f"{path}: malformed checkpoint ({error})") from None


def latest_valid_checkpoint(directory: Path) -> Checkpoint | None:
    """The newest checkpoint that loads; corrupt newer ones are reported and skipped."""
    for path in sorted(directory.glob("round-*.ckpt"), reverse=True):
        try:
            return load_checkpoint(path)
        except CheckpointError as error:
            logger.warning("skipping checkpoint: %s", error)
    return None


def completed_round(directory: Path, rounds: int) -> int | None:
    """The round of the newest valid checkpoint in ``directory`` when it is at or past
    ``rounds`` (the run is complete: resuming it has nothing to run), else None."""
    if not directory.is_dir():
        return None
    checkpoint = latest_valid_checkpoint(directory)
    return checkpoint.round if checkpoint is not None and checkpoint.round >= rounds else None


def complete_message(run_dir: Path, round_number: int) -> str:
    """What a resume of a complete run says instead of starting anything."""
    return (
        f"{run_dir} is complete: round {round_number} of rounds={round_number}, nothing to run "
        f"(resume with rounds=N above {round_number} to continue it)\n"
    )


def interrupted_message(run_dir: Path, resume_command: str) -> str:
    """Where a stopped run is and how to continue it (one line)."""
    checkpoint = latest_valid_checkpoint(run_dir / "checkpoints") if run_dir.is_dir() else None
    if checkpoint is None:
        return f"interrupted before the first round was saved; nothing to resume in {run_dir}"
    return (
        f"interrupted after round {checkpoint.round}; run directory: {run_dir.resolve()}; "
        f"continue it with: {resume_command}"
    )
