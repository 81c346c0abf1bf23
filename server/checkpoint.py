"""Per-round checkpoints in safetensors: tensors and a JSON header, a SHA-256 of both, atomic
writes, no pickle; any torch tool reads θ̃ (``safetensors.torch.load_file(path)["theta"]``).

A checkpoint holds everything a killed server needs to continue exactly: θ̃, the round, the
strategy's state (whatever :meth:`Strategy.state` returned, e.g. fedadam's moments), the run's
counters (``state``) and how many ``metrics.jsonl`` lines belong to it. There are no
random-number states to keep: every random stream of a run is derived from (seed, agent,
round, purpose) where it is used.

``round-NNNNNN.safetensors`` (format version 4): the tensors ``theta``, ``strategy/<name>``
and ``schedule/<name>``; the header's metadata holds the round, the config, the counters and
the strategy's and schedule's scalars as JSON, and ``sha256``, the digest of everything else
(:func:`_digest`). Files of the msgpack format before it (``round-NNNNNN.ckpt``, versions 1
to 3) are still read, so a run checkpointed in it resumes; the newest valid file of either
kind is the one taken.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import logging
import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load, save

from fedhpg.common.records.types import SavedState

logger = logging.getLogger(__name__)
T = TypeVar("T")

CHECKPOINT_FORMAT = "fedhpg-checkpoint"
CHECKPOINT_VERSION = 4
"""4: safetensors. The msgpack files before it: 3 kept the strategy's state under ``strategy``;
2 kept the server optimizer's in ``state`` and ``server_optimizer.*`` arrays (read as the
strategy's state)."""
READABLE_VERSIONS = (1, 2, 3)
"""The msgpack format's versions still read."""
KEEP_CHECKPOINTS = 2
SUFFIX = ".safetensors"
LEGACY_SUFFIX = ".ckpt"
BEST_NAME = f"best{SUFFIX}"
"""``checkpoint.keep_best``: the best evaluation's checkpoint, beside the rolling ones."""
KEPT_DIR = "kept"
"""``checkpoint.every``: every N-th round's checkpoint, in this folder of the checkpoints'
(never rotated away)."""
BEST_RETURN = "best_return"
"""The best checkpoint's ``state`` key: its evaluation's mean return over the agents."""


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


def _unpack_array(packed: dict[str, Any]) -> np.ndarray:
    dtype = np.dtype(packed["dtype"])
    if dtype.kind not in "fiub":  # plain numbers only: an object dtype would mean pickle
        raise ValueError(f"array dtype {dtype} is not allowed")
    return np.frombuffer(packed["data"], dtype=dtype).reshape(packed["shape"]).copy()


def checkpoint_path(directory: Path, round_number: int) -> Path:
    return directory / f"round-{round_number:06d}{SUFFIX}"


def _round_of(path: Path) -> int:
    try:
        return int(path.name.split(".", 1)[0].removeprefix("round-"))
    except ValueError:
        return -1


def checkpoint_files(directory: Path) -> list[Path]:
    """The checkpoint files in ``directory``, oldest first (the safetensors file after a
    msgpack one of the same round)."""
    paths = [*directory.glob(f"round-*{SUFFIX}"), *directory.glob(f"round-*{LEGACY_SUFFIX}")]
    return sorted(paths, key=lambda p: (_round_of(p), p.suffix == SUFFIX))


def _unpack_state(saved: dict[str, Any]) -> SavedState:
    return SavedState(
        scalars=dict(saved["scalars"]),
        arrays={name: _unpack_array(a) for name, a in saved["arrays"].items()},
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


def _digest(metadata: dict[str, str], tensors: dict[str, np.ndarray]) -> str:
    """SHA-256 of a checkpoint's content: its metadata (but the digest) as sorted JSON, then
    each tensor's name, dtype, shape and bytes in name order."""
    digest = hashlib.sha256(json.dumps(metadata, sort_keys=True).encode())
    for name in sorted(tensors):
        array = tensors[name]
        digest.update(f"|{name}|{array.dtype.str}|{list(array.shape)}|".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def _safetensors_bytes(checkpoint: Checkpoint) -> bytes:
    tensors = {"theta": checkpoint.theta.detach().cpu().numpy()}
    tensors |= {f"strategy/{k}": v for k, v in checkpoint.strategy.arrays.items()}
    metadata = {
        "format": CHECKPOINT_FORMAT,
        "version": str(CHECKPOINT_VERSION),
        "round": str(checkpoint.round),
        "metrics_lines": str(checkpoint.metrics_lines),
        "config": json.dumps(checkpoint.config),
        "state": json.dumps(checkpoint.state),
        "strategy": json.dumps(checkpoint.strategy.scalars),
    }
    if checkpoint.schedule is not None:
        tensors |= {f"schedule/{k}": v for k, v in checkpoint.schedule.arrays.items()}
        metadata["schedule"] = json.dumps(checkpoint.schedule.scalars)
    tensors = {name: np.ascontiguousarray(array) for name, array in tensors.items()}
    metadata["sha256"] = _digest(metadata, tensors)
    return bytes(save(tensors, metadata=metadata))


def save_checkpoint(
    directory: Path, checkpoint: Checkpoint, *, keep_every: int | None = None
) -> Path:
    """Write this round's checkpoint atomically and prune all but the newest few; with
    ``keep_every`` N, a round that is a multiple of N is also written to ``kept/`` (written
    before anything is pruned)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = checkpoint_path(directory, checkpoint.round)
    data = _safetensors_bytes(checkpoint)
    write_atomic(path, data)
    if keep_every is not None and checkpoint.round % keep_every == 0:
        (directory / KEPT_DIR).mkdir(exist_ok=True)
        write_atomic(checkpoint_path(directory / KEPT_DIR, checkpoint.round), data)
    for old in checkpoint_files(directory)[:-KEEP_CHECKPOINTS]:
        old.unlink(missing_ok=True)
    return path


def save_best(directory: Path, checkpoint: Checkpoint, mean_return: float) -> Path:
    """Write ``checkpoint`` atomically as the best so far (``best.safetensors``), its mean
    evaluation return in its state (:data:`BEST_RETURN`)."""
    directory.mkdir(parents=True, exist_ok=True)
    best = dataclasses.replace(checkpoint, state={**checkpoint.state, BEST_RETURN: mean_return})
    path = directory / BEST_NAME
    write_atomic(path, _safetensors_bytes(best))
    return path


def best_checkpoint(directory: Path) -> Checkpoint | None:
    """The best evaluation's checkpoint (``checkpoint.keep_best``), None where there is none;
    CheckpointError where it is damaged."""
    path = directory / BEST_NAME
    return load_checkpoint(path) if path.exists() else None


def _header(raw: bytes, path: Path) -> dict[str, Any]:
    """A safetensors file's JSON header (8 bytes of length, then the JSON)."""
    if len(raw) < 8:
        raise CheckpointError(f"{path}: torn or corrupt file (shorter than its header)")
    (length,) = struct.unpack("<Q", raw[:8])
    if length > len(raw) - 8:
        raise CheckpointError(f"{path}: torn or corrupt file (its header runs past its end)")
    try:
        header = json.loads(raw[8 : 8 + length])
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise CheckpointError(f"{path}: torn or corrupt file (no safetensors header)") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: not a safetensors file")
    return header


def _load_safetensors(path: Path, raw: bytes) -> Checkpoint:
    metadata = _header(raw, path).get("__metadata__") or {}
    if metadata.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} file")
    if metadata.get("version") != str(CHECKPOINT_VERSION):
        raise CheckpointError(
            f"{path}: version {metadata.get('version')!r} of the checkpoint format; this fedhpg "
            f"reads version {CHECKPOINT_VERSION} (and the msgpack files of 1 to 3)"
        )
    try:
        tensors = load(raw)
    except (SafetensorError, ValueError) as error:
        raise CheckpointError(f"{path}: torn or corrupt file ({error})") from None
    unsigned = {k: v for k, v in metadata.items() if k != "sha256"}
    if metadata.get("sha256") != _digest(unsigned, tensors):
        raise CheckpointError(f"{path}: checksum mismatch (torn or corrupt file)")
    try:
        theta = tensors["theta"]
        strategy = SavedState(
            scalars=dict(json.loads(metadata["strategy"])),
            arrays={k[9:]: v for k, v in tensors.items() if k.startswith("strategy/")},
        )
        schedule = None
        if "schedule" in metadata:
            schedule = SavedState(
                scalars=dict(json.loads(metadata["schedule"])),
                arrays={k[9:]: v for k, v in tensors.items() if k.startswith("schedule/")},
            )
        values = {
            "round": int(metadata["round"]),
            "metrics_lines": int(metadata["metrics_lines"]),
            "config": json.loads(metadata["config"]),
            "state": dict(json.loads(metadata["state"])),
        }
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: malformed checkpoint ({error})") from None
    return _checked(
        path,
        theta,
        strategy=strategy,
        schedule=schedule,
        version=CHECKPOINT_VERSION,
        **values,
    )


def _checked(path: Path, theta: np.ndarray, **fields: Any) -> Checkpoint:
    if theta.dtype != np.float32 or theta.ndim != 1 or not np.isfinite(theta).all():
        raise CheckpointError(f"{path}: θ̃ is not a finite float32 vector")
    return Checkpoint(theta=torch.from_numpy(theta.copy()), **fields)


def load_checkpoint(path: Path) -> Checkpoint:
    """The checkpoint in ``path`` (safetensors, or the msgpack format before it), or
    CheckpointError saying in one line why it cannot be used."""
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise CheckpointError(f"{path}: cannot read ({error.strerror})") from None
    if path.suffix == SUFFIX:
        return _load_safetensors(path, raw)
    return _load_msgpack(path, raw)


def _load_msgpack(path: Path, raw: bytes) -> Checkpoint:
    """A file of the msgpack format (versions 1 to 3): a SHA-256, then msgpack with raw
    array bytes."""
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
        return _checked(
            path,
            _unpack_array(values["theta"]),
            round=int(values["round"]),
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


_REPORTED: set[tuple[str, int, int]] = set()
"""(path, size, mtime) of the damaged files warned about: a resume reads the checkpoints more
than once (is the run complete, then its resume point; on an interrupt, where to continue),
in one process or its forked server; a file damaged again since is warned about again."""


def latest_valid_checkpoint(directory: Path) -> Checkpoint | None:
    """The newest checkpoint that loads; corrupt newer ones are reported (once each) and
    skipped."""
    for path in reversed(checkpoint_files(directory)):
        try:
            return load_checkpoint(path)
        except CheckpointError as error:
            try:
                stat = path.stat()
                seen = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
            except OSError:
                seen = (str(path), -1, -1)
            if seen not in _REPORTED:
                _REPORTED.add(seen)
                logger.warning("skipping checkpoint: %s", error)
    return None


def completed_round(directory: Path, rounds: int) -> int | None:
    """The round of the newest valid checkpoint in ``directory`` when the run is complete at
    ``rounds`` (checkpointed at that round, and ``rounds`` not below the run's own, which a
    resume refuses), else None."""
    if not directory.is_dir():
        return None
    checkpoint = latest_valid_checkpoint(directory)
    if checkpoint is None or checkpoint.round < rounds:
        return None
    planned = int(checkpoint.config.get("rounds", checkpoint.round))
    return checkpoint.round if rounds >= planned else None


def complete_message(run_dir: Path, round_number: int) -> str:
    """What a resume of a complete run says instead of starting anything."""
    return (
        f"{run_dir} is complete: round {round_number} of rounds={round_number}, nothing to run "
        f"(resume with rounds=N above {round_number} to continue it)\n"
    )


def nothing_to_run(run_dir: Path, rounds: int, stop_at: float | None) -> str | None:
    """What a resume of the run in ``run_dir`` with ``rounds`` and ``eval.stop_at`` says
    instead of starting anything (one line): the run is complete, or stopped at the target the
    resume keeps. None when there is a round to run."""
    done = completed_round(run_dir / "checkpoints", rounds)
    if done is not None:
        return complete_message(run_dir, done)
    return stopped_early_message(run_dir, stop_at)


def stopped_early_message(run_dir: Path, stop_at: float | None) -> str | None:
    """What a resume says instead of starting anything when the run stopped at
    ``eval.stop_at`` (``summary.json``'s ``stopped_early``, at its newest valid checkpoint) and
    the resume keeps that target; None otherwise. As with a complete run, one line and
    nothing run: the target is reached."""
    try:
        summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    stopped = summary.get("stopped_early") if isinstance(summary, dict) else None
    if not isinstance(stopped, dict) or stopped.get("stop_at") != stop_at:
        return None
    checkpoint = latest_valid_checkpoint(run_dir / "checkpoints")
    if checkpoint is None or checkpoint.round != stopped.get("round"):
        return None  # resumed since, past the round it stopped at
    return (
        f"{run_dir} stopped early: round {checkpoint.round}'s evaluation reached "
        f"eval.stop_at={stop_at:g}, nothing to run (resume with another eval.stop_at, or "
        "eval.stop_at=null, to continue it)\n"
    )


def interrupted_message(run_dir: Path, resume_command: str) -> str:
    """Where a stopped run is and how to continue it (one line)."""
    checkpoint = latest_valid_checkpoint(run_dir / "checkpoints") if run_dir.is_dir() else None
    if checkpoint is None and (run_dir / "config.json").is_file():
        return (
            f"interrupted before the first round was saved; run directory: {run_dir.resolve()}; "
            f"start it again from round 0 with: {resume_command}"
        )
    if checkpoint is None:
        return f"interrupted before the first round was saved; nothing to resume in {run_dir}"
    return (
        f"interrupted after round {checkpoint.round}; run directory: {run_dir.resolve()}; "
        f"continue it with: {resume_command}"
    )
