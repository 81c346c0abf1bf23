"""What makes a directory hold a run, shared by the server's run directory and ``resume=auto``."""

from __future__ import annotations

from pathlib import Path

METRICS_NAME = "metrics.jsonl"
RUN_FILES = (METRICS_NAME, "summary.json", "checkpoints")
"""What makes a directory hold a run: rounds or results. (A ``config.json`` alone, left by a
server that could not bind, does not; nor do Hydra's ``.hydra/`` and logs.)"""


def holds_run(path: Path) -> bool:
    return any((path / name).exists() for name in RUN_FILES)
