"""A run's rounds for the tools people read them with, beside ``metrics.jsonl`` (the source of
truth): ``progress.csv`` (a spreadsheet's view, one row per round) and Weights & Biases
(``server.wandb``, the optional ``wandb`` package). TensorBoard's event files are written by
:mod:`fedhpg.server.metrics`; W&B shows the same keys
(:class:`~fedhpg.server.metrics.RoundValues`).
"""

from __future__ import annotations

import csv
import hashlib
import logging
import math
from pathlib import Path
from typing import Any

import torch

from fedhpg.common.configuration.config import RunConfig, to_dict
from fedhpg.common.configuration.run_keys import flatten
from fedhpg.common.runtime.run_files import WANDB_DIR
from fedhpg.server.coordinator import RoundRecord
from fedhpg.server.metrics import RoundValues
from fedhpg.server.run_dir import RunDirectoryError

logger = logging.getLogger(__name__)


class ProgressCsv:
    """``progress.csv``: a row per round, flushed as written. Columns: round, wall and round
    time, the slowest agent's emulated time, trajectories per agent, updates aggregated, the
    mean training return, and on evaluated rounds the unified policy's mean and worst return
    (and mean success rate where the environment has a goal); empty cells elsewhere. A resumed
    run keeps the rows before its first round and drops the rest."""

    def __init__(self, path: Path, *, first_round: int = 1, has_goal: bool = False) -> None:
        self.path = path
        self.columns = [
            "round",
            "wall_time_s",
            "round_time_s",
            "emulated_round_s",
            "trajectories_per_agent",
            "updates",
            "train_return_mean",
            "eval_return_mean",
            "eval_return_min",
            *(["eval_success_mean"] if has_goal else []),
        ]
        kept: list[list[str]] = []
        if first_round > 1 and path.exists():
            with path.open(newline="", encoding="utf-8") as handle:
                rows = list(csv.reader(handle))
            kept = [
                row for row in rows[1:] if row and row[0].isdigit() and int(row[0]) < first_round
            ]
        self._file = path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(self.columns)
        self._writer.writerows(kept)
        self._file.flush()

    def __call__(self, record: RoundRecord, _: torch.Tensor) -> None:
        stats = record.result.stats
        row: dict[str, Any] = {
            "round": record.round,
            "wall_time_s": record.wall_time_s,
            "round_time_s": record.round_time_s,
            "emulated_round_s": max(stats.emulated_s, default=None),
            "trajectories_per_agent": record.trajectories_per_agent,
            "updates": record.update_count,
            "train_return_mean": _mean(stats.train_return),
        }
        if record.eval:
            returns = [e.return_mean for e in record.eval.values()]
            row["eval_return_mean"] = _mean(returns)
            row["eval_return_min"] = min(returns)
            row["eval_success_mean"] = _mean([e.success_rate for e in record.eval.values()])
        try:
            self._writer.writerow([_cell(row.get(column)) for column in self.columns])
            self._file.flush()
        except OSError as error:
            raise RunDirectoryError(
                f"cannot write round {record.round} to {self.path}: {error.strerror or error}"
            ) from None

    def close(self) -> None:
        self._file.close()


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def _cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return f"{value:.6g}" if isinstance(value, float) else str(value)


class WandbSink:
    """Every round's :class:`~fedhpg.server.metrics.RoundValues` as a W&B run's history, step =
    round; the config as the run's config. The run's id is derived from the run directory, so
    a resumed run continues its W&B run (from the first round it runs again)."""

    def __init__(self, run: RunConfig, out_dir: Path, theta: torch.Tensor) -> None:
        import wandb

        self._values = RoundValues(
            theta, per_agent=run.agents.num_agents <= run.server.tensorboard_agents
        )
        directory = out_dir / WANDB_DIR
        directory.mkdir(parents=True, exist_ok=True)
        identity = hashlib.sha256(str(out_dir.resolve()).encode()).hexdigest()[:16]
        self._run = wandb.init(
            project=run.server.wandb_project,
            name=out_dir.name,
            id=identity,
            resume="allow",
            dir=str(out_dir),
            config=flatten(to_dict(run)),
            settings=wandb.Settings(console="off", silent=True),
        )

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> None:
        self._run.log(self._values(record, theta), step=record.round)

    def close(self) -> None:
        self._run.finish()


def wandb_sink(run: RunConfig, out_dir: Path, theta: torch.Tensor) -> WandbSink | None:
    """The W&B sink of ``server.wandb`` runs, or None (off, or ``wandb`` not installed: a
    warning, and the run goes on with its other files)."""
    if not run.server.wandb:
        return None
    try:
        import wandb  # noqa: F401
    except ImportError:
        logger.warning(
            "wandb is not installed (pip install 'fedhpg[wandb]'): no W&B run, the run "
            "directory's files only (server.wandb=false silences this)"
        )
        return None
    return WandbSink(run, out_dir, theta)
