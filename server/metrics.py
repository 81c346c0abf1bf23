"""Round metrics: one JSON object per line in ``metrics.jsonl`` (schema: docs/metrics.md), and
the same rounds as TensorBoard scalars beside it."""

from __future__ import annotations

import functools
import itertools
import json
import logging
import math
import operator
import os
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np
import orjson
import torch

from fedhpg.common.configuration.config import RunConfig, attacking_agents, to_dict
from fedhpg.common.configuration.run_keys import flatten
from fedhpg.common.configuration.run_roles import groups
from fedhpg.common.records.types import ALWAYS_FIELDS, RoundResult
from fedhpg.common.runtime.run_files import TENSORBOARD_DIR
from fedhpg.server.coordinator import RoundRecord
from fedhpg.server.run_dir import RunDirectoryError

logger = logging.getLogger(__name__)

METRICS_SCHEMA_VERSION = 1
SECURE_MODES = ("secagg", "dp_secagg")


def record_marks(run: RunConfig) -> dict[str, Any]:
    """What every line of a run's metrics.jsonl carries besides its round: the attacking
    agents (``attack``: kind and indices) when some attack."""
    attackers = attacking_agents(run)
    return {"attack": {"kind": run.attack.kind, "agents": attackers}} if attackers else {}


def metrics_line(record: RoundRecord, marks: dict[str, Any] | None = None) -> dict[str, Any]:
    """A round's metrics.jsonl object (schema: docs/metrics.md)."""
    return {"schema": METRICS_SCHEMA_VERSION, **record.to_json(), **(marks or {})}


class MetricsWriter:
    """Appends a line per round and flushes it to disk, so a crash loses at most one round."""

    def __init__(self, path: Path, *, marks: dict[str, Any] | None = None) -> None:
        self.path = path
        self.marks = marks or {}
        """Keys every line carries (:func:`record_marks`)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = path.open("a", encoding="utf-8")

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> None:
        line = metrics_line(record, self.marks)
        try:
            # orjson: an order of magnitude faster than json.dumps on a large round's rows, time
            # the next round waits for; the same JSON values, written compactly
            self._file.write(orjson.dumps(line, option=orjson.OPT_NON_STR_KEYS).decode() + "\n")
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError as error:
            raise RunDirectoryError(
                f"cannot write round {record.round} to {self.path}: {error.strerror or error}; "
                "the rounds before it are in the file and the checkpoints"
            ) from None

    def close(self) -> None:
        self._file.close()


def read_metrics(path: Path) -> list[dict[str, Any]]:
    with path.open(encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.strip()]


# --- TensorBoard, CSV, W&B: views of the same records (metrics.jsonl stays the truth) -----


NORM_ROWS = 256
"""Rows of θ_k taken to float64 at a time for the update norms (not the whole [K, d] block:
at K = 1,000 and d = 10⁴ that copy would be 80 MB)."""


def _update_norms(result: RoundResult, before: np.ndarray) -> dict[int, float]:
    """‖θ_k − θ̃_before‖ per agent index, a slab of rows per numpy call rather than a call per
    agent, over the round's [K, d] block."""
    norms: dict[int, float] = {}
    order = result.agents
    for start in range(0, len(order), NORM_ROWS):
        slab = result.thetas[start : start + NORM_ROWS].astype(np.float64)
        slab -= before
        rows = np.sqrt(np.einsum("ij,ij->i", slab, slab)).tolist()  # no temporaries per slab
        norms.update(zip(order[start : start + NORM_ROWS], rows, strict=True))
    return norms


def _columns(result: RoundResult, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Each statistic of the round's ``agents[]`` rows as a column, without its missing values
    (rows differ in keys: an algorithm's own, ``local_wall_s`` where measured). A column per
    statistic, not a loop over every agent's every value: the record is written while the next
    round's agents train, on a core they could use."""
    columns: dict[str, Any] = {
        name: np.fromiter(map(operator.itemgetter(name), rows), np.float64, len(rows))
        for name in ALWAYS_FIELDS
    }
    stats = result.stats
    measured = any(v is not None for v in stats.local_wall_s)
    optional = dict.fromkeys(itertools.chain(["local_wall_s"] if measured else [], stats.algorithm))
    for name in optional:
        columns[name] = [v for row in rows if (v := row.get(name)) is not None]
    return columns


_NOT_SCALARS = frozenset({"id", "index"})
"""Keys of an ``agents[]`` row that name the agent rather than measure its update."""


class RoundValues:
    """The scalars of each round under grouped keys, step = round: ``fed/…`` for the
    federation, ``agent/<k>/…`` for agent k's update, ``agents/<stat>/{mean,min,max}`` for their
    spread, ``eval/<id>/…`` (and ``eval/mean/…``) for the unified policy's evaluation. Keys:
    docs/metrics.md. TensorBoard and W&B show the same values."""

    def __init__(self, theta: torch.Tensor, *, per_agent: bool = True) -> None:
        self._previous = theta.detach().numpy().astype(np.float64)
        """θ̃ before the round: the update norms are measured from it."""
        self._per_agent = per_agent
        """Write ``agent/<k>/…`` and ``eval/<id>/…`` (``server.tensorboard_agents``): at 1,000
        agents they are 14,000 values a round, and more curves than anyone reads."""

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> dict[str, float]:
        """The round's values (finite ones only: NaN/Inf never reach metrics.jsonl either)."""
        after = theta.detach().numpy().astype(np.float64)
        values = self._values(record, after)
        self._previous = after
        return {key: float(value) for key, value in values.items() if math.isfinite(value)}

    def _values(self, record: RoundRecord, after: np.ndarray) -> dict[str, float]:
        before = self._previous
        values: dict[str, float] = {
            "fed/round_time_s": record.round_time_s,
            "fed/wall_time_s": record.wall_time_s,
            "fed/trajectories_per_agent": record.trajectories_per_agent,
            "fed/updates": record.update_count,
            "fed/failures": len(record.failures),
            "fed/stragglers": len(record.stragglers),
            "fed/theta_norm": float(np.linalg.norm(after)),
            "fed/theta_step_norm": float(np.linalg.norm(after - before)),
        }
        if len(record.result):
            stats = record.result.stats
            # The round's emulated duration is its slowest agent's emulated time.
            values["fed/emulated_round_s"] = max(stats.emulated_s)
            values["fed/trajectories"] = sum(stats.trajectories)
        if record.privacy is not None:
            for key in ("epsilon", "epsilon_server", "delta", "noise_multiplier", "clip", "inputs"):
                if key in record.privacy:
                    values[f"privacy/{key}"] = record.privacy[key]
        # under secure aggregation the server holds no θ_k: there are no update norms
        secure = record.privacy is not None and record.privacy["mode"] in SECURE_MODES
        norms = {} if secure else _update_norms(record.result, before)
        rows = record.agent_rows
        across = _columns(record.result, rows)
        if not secure:
            across["update_norm"] = [norms[row["index"]] for row in rows]
        across = {name: column for name, column in across.items() if len(column)}
        if self._per_agent:
            for row in rows:
                index = row["index"]
                norm = () if secure else (("update_norm", norms[index]),)
                for name, value in itertools.chain(row.items(), norm):
                    if value is not None and name not in _NOT_SCALARS:
                        values[f"agent/{index}/{name}"] = value
        for name, column in across.items():  # the spread over the round's agents
            spread = np.asarray(column, dtype=np.float64)
            values[f"agents/{name}/mean"] = float(spread.mean())
            values[f"agents/{name}/min"] = float(spread.min())
            values[f"agents/{name}/max"] = float(spread.max())
        if record.eval:
            for agent, evaluation in record.eval.items() if self._per_agent else ():
                values[f"eval/{agent}/return"] = evaluation.return_mean
                values[f"eval/{agent}/discounted_return"] = evaluation.discounted_return_mean
                values[f"eval/{agent}/success_rate"] = evaluation.success_rate
                values[f"eval/{agent}/length"] = evaluation.length_mean
            evaluations = list(record.eval.values())
            values["eval/mean/return"] = float(np.mean([e.return_mean for e in evaluations]))
            values["eval/mean/success_rate"] = float(np.mean([e.success_rate for e in evaluations]))
            values["eval/min/return"] = min(e.return_mean for e in evaluations)
        return values


HPARAM_METRICS = ("eval/mean/return", "eval/min/return", "fed/trajectories_per_agent")
"""The scalars TensorBoard's HParams dashboard compares runs by."""


def hyperparameters(run: RunConfig) -> dict[str, int | float | str | bool]:
    """What tells runs apart, for TensorBoard's HParams dashboard and W&B's config: every key
    of the groups plots compare runs by, and the seed (lists and dicts as text)."""
    values = to_dict(run)
    chosen = {key: values[key] for key in (*groups("compared"), "seed", "rounds")}
    flat: dict[str, int | float | str | bool] = {}
    for key, value in flatten(chosen).items():
        if isinstance(value, bool | int | float | str):
            flat[key] = value
        elif value is not None and value != {} and value != []:
            flat[key] = json.dumps(value)
    return flat


class EventFile:
    """One TensorBoard event file, its records written on the caller's thread, flushed as each
    is written: a disk that fills up is an OSError here (the run directory's one-line error),
    not a traceback in a writer thread. Each record is framed as tensorboard's own
    ``RecordWriter`` frames it, byte for byte (:func:`tf_record`)."""

    def __init__(self, directory: Path) -> None:
        from tensorboard.compat.proto.event_pb2 import Event

        directory.mkdir(parents=True, exist_ok=True)
        name = (
            f"events.out.tfevents.{_sorting_stamp(directory):010d}.{socket.gethostname()}."
            f"{os.getpid()}.{next(_files_opened)}"
        )
        self._file = (directory / name).open("wb")
        self._event = Event
        self.add(Event(wall_time=time.time(), file_version="brain.Event:2"))

    def add(self, event: Any) -> None:
        self._file.write(tf_record(event.SerializeToString()))
        self._file.flush()

    def close(self) -> None:
        self._file.close()


_files_opened = itertools.count()


def tf_record(data: bytes) -> bytes:
    """``data`` as one TFRecord: its length (uint64), the length's masked CRC-32C, the data,
    the data's masked CRC-32C (little-endian), as tensorboard's ``RecordWriter`` writes it."""
    masked_crc32c = _masked_crc32c()
    length = struct.pack("<Q", len(data))
    return b"".join((length, struct.pack("<I", masked_crc32c(length)), data,
                     struct.pack("<I", masked_crc32c(data))))  # fmt: skip


@functools.cache
def _masked_crc32c() -> Callable[[bytes], int]:
    """TFRecord's masked CRC-32C, with google-crc32c's compiled CRC where it is installed (the
    tensorboard extra). Tensorboard's own is pure Python (TensorFlow's is not a dependency):
    about 0.1 µs a byte, 3 ms of the server's round for the 30 KB event of 100 agents'
    values, against 1 µs."""
    try:
        import google_crc32c
    except ImportError:  # tensorboard alone: its own
        from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c

        return cast(Callable[[bytes], int], masked_crc32c)

    def masked(data: bytes) -> int:
        crc = google_crc32c.value(data)
        return (((crc >> 15) | (crc << 17)) + _CRC_MASK_DELTA) & 0xFFFFFFFF

    return masked


_CRC_MASK_DELTA = 0xA282EAD8
"""TFRecord's CRC mask: rotate right by 15 bits, add this."""


def _sorting_stamp(directory: Path) -> int:
    """The seconds field of a new event file's name: now, or one past the newest file already
    in ``directory`` when that one is not older. TensorBoard reads a run's files in the order
    of their names and a later file's purge applies only to what it read before, so a resumed
    run's file must sort last even when it opens within the second of the one before (the
    host, pid and counter fields after the seconds do not sort in opening order)."""
    now = int(time.time())
    stamps = []
    for path in directory.glob("events.out.tfevents.*"):
        field = path.name.split(".")[3]
        if field.isdigit():
            stamps.append(int(field))
    return max([now, *(stamp + 1 for stamp in stamps)])


class TensorBoardWriter:
    """The rounds' scalars (:class:`RoundValues`) in a TensorBoard event file
    (:class:`EventFile`), one event per round (one summary of many values); the run's
    hyperparameters for the HParams dashboard first."""

    def __init__(
        self,
        directory: Path,
        theta: torch.Tensor,
        *,
        hparams: dict[str, int | float | str | bool],
        first_round: int = 1,
        per_agent: bool = True,
    ) -> None:
        from tensorboard.compat.proto.event_pb2 import Event, SessionLog
        from tensorboard.compat.proto.summary_pb2 import Summary

        self._event, self._summary = Event, Summary
        self._file = EventFile(directory)
        self._values = RoundValues(theta, per_agent=per_agent)
        if first_round > 1:
            # TensorBoard's purge: readers drop the older events of this step and later ones
            self._file.add(Event(step=first_round, session_log=SessionLog(status=SessionLog.START)))
        for summary in _hparams_summaries(hparams):
            self._file.add(Event(wall_time=time.time(), summary=summary))

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> None:
        summary = self._summary(
            value=[
                self._summary.Value(tag=key, simple_value=value)
                for key, value in self._values(record, theta).items()
            ]
        )
        event = self._event(wall_time=time.time(), step=record.round, summary=summary)
        try:
            self._file.add(event)
        except OSError as error:
            raise RunDirectoryError(
                f"cannot write round {record.round}'s TensorBoard event: "
                f"{error.strerror or error}; metrics.jsonl and the checkpoints hold the rounds"
            ) from None

    def close(self) -> None:
        self._file.close()


def _hparams_summaries(hparams: dict[str, int | float | str | bool]) -> list[Any]:
    """The HParams plugin's experiment and session-start summaries for one run."""
    from tensorboard.plugins.hparams import summary_v2

    metrics = [summary_v2.Metric(tag) for tag in HPARAM_METRICS]
    experiment = summary_v2.hparams_config_pb(
        hparams=[summary_v2.HParam(name) for name in hparams], metrics=metrics
    )
    session = summary_v2.hparams_pb(hparams, start_time_secs=int(time.time()))
    return [experiment, session]


def tensorboard_sink(
    run: RunConfig,
    out_dir: Path,
    *,
    first_round: int,
    theta: torch.Tensor,
) -> TensorBoardWriter | None:
    """A TensorBoard writer for ``out_dir/tensorboard``, or None when off or not installed.

    A resumed run (``first_round`` > 1) purges the steps from ``first_round`` on that an
    earlier process wrote, so no round is shown twice."""
    if not run.server.tensorboard:
        return None
    try:
        from tensorboard.compat.proto.event_pb2 import Event  # noqa: F401
        from tensorboard.summary.writer.record_writer import RecordWriter  # noqa: F401
    except ImportError:
        logger.warning(
            "tensorboard is not installed (pip install 'fedhpg[tensorboard]'): no event "
            "files, metrics.jsonl only (server.tensorboard=false silences this)"
        )
        return None
    return TensorBoardWriter(
        out_dir / TENSORBOARD_DIR,
        theta,
        hparams=hyperparameters(run),
        first_round=first_round,
        per_agent=run.agents.num_agents <= run.server.tensorboard_agents,
    )
