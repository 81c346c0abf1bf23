"""Round metrics: one JSON object per line in ``metrics.jsonl`` (schema: docs/metrics.md)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from fedhpg.server.coordinator import RoundRecord
from fedhpg.server.run_dir import RunDirectoryError

METRICS_SCHEMA_VERSION = 1


class MetricsWriter:
    """Appends a line per round and flushes it to disk, so a crash loses at most one round."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = path.open("a", encoding="utf-8")

    def __call__(self, record: RoundRecord, theta: torch.Tensor) -> None:
        line: dict[str, Any] = {"schema": METRICS_SCHEMA_VERSION, **record.to_json()}
        try:
            self._file.write(json.dumps(line) + "\n")
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
