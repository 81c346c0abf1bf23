"""What makes a directory hold a run, shared by the server's run directory and ``resume=auto``,
and how every entry point names a new one."""

from __future__ import annotations

import time
from pathlib import Path

METRICS_NAME = "metrics.jsonl"
CONFIG_NAME = "config.json"
"""The resolved config a run ran with, what ``resume=`` starts from."""
RUN_LOG_NAME = "run.log"
"""The server's log lines (INFO and above) of every start of the run, appended."""
PROGRESS_NAME = "progress.csv"
TENSORBOARD_DIR = "tensorboard"
WANDB_DIR = "wandb"
RUN_FILES = (METRICS_NAME, "summary.json", "checkpoints")
"""What makes a directory hold a run: rounds or results. (A ``config.json`` alone, left by a
server that could not bind, does not; nor do Hydra's ``.hydra/`` and logs.)"""


def holds_run(path: Path) -> bool:
    return any((path / name).exists() for name in RUN_FILES)


RUNS_ROOT = Path("runs")
"""Where every entry point makes a run's directory when none is named (``server.out_dir``)."""


def run_label(family: str, env_id: str | None, algorithm: str) -> str:
    """What a run directory's name says after its date and time: the environment (the
    gymnasium id of ``env=gym``) and the algorithm, as characters a path takes."""
    environment = env_id if family == "gym" and env_id else family
    text = f"{environment}-{algorithm}"
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


def new_run_path(label: str, *, root: Path = RUNS_ROOT, now: float | None = None) -> Path:
    """A new run directory's path: ``runs/<YYYYmmdd>-<HHMMSS>-<label>``, with ``-2``, ``-3``
    … where one of that name exists. (Not created: the server claims it.)"""
    base = f"{time.strftime('%Y%m%d-%H%M%S', time.localtime(now))}-{label}"
    path, number = root / base, 2
    while path.exists():
        path, number = root / f"{base}-{number}", number + 1
    return path


_HYDRA_RUN_DIRS: dict[tuple[str, str | None, str], str] = {}


def hydra_run_dir(family: str, env_id: str | None, algorithm: str) -> str:
    """The resolver ``${fedhpg_run_dir:...}`` of ``hydra.run.dir`` (conf/config.yaml): the
    same path however often Hydra resolves it in a process, so that ``fedhpg-run``'s run
    directory follows the one convention."""
    key = (str(family), None if env_id in (None, "None") else str(env_id), str(algorithm))
    if key not in _HYDRA_RUN_DIRS:
        _HYDRA_RUN_DIRS[key] = str(new_run_path(run_label(*key)))
    return _HYDRA_RUN_DIRS[key]
