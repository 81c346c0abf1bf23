"""A start that fails before its first round leaves nothing of its own in the run directory,
never anything it found there; a refused claim or resume leaves no ``.lock`` it made."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.server.run_dir import LOCK_NAME, RunDirectory, claimed


def _start(run_dir: RunDirectory, *, rounds: int = 0) -> None:
    """What a server writes before (and in) its first rounds."""
    (run_dir.path / "config.json").write_text("{}")
    (run_dir.path / "metrics.jsonl").write_text(
        "".join(json.dumps({"round": r}) + "\n" for r in range(1, rounds + 1))
    )
    (run_dir.path / "tensorboard").mkdir()
    (run_dir.path / "tensorboard" / "events").write_text("x")


def test_a_failed_start_removes_the_directories_it_made(tmp_path: Path) -> None:
    path = tmp_path / "runs" / "new"
    with pytest.raises(ConfigError), claimed(path, resume=False) as run_dir:
        _start(run_dir)
        raise ConfigError("rounds", "refused by the server")
    assert not (tmp_path / "runs").exists()


def test_a_failed_start_keeps_what_the_directory_held(tmp_path: Path) -> None:
    path = tmp_path / "mine"
    path.mkdir()
    (path / "notes.txt").write_text("the user's")
    with pytest.raises(RuntimeError), claimed(path, resume=False) as run_dir:
        _start(run_dir)
        (path / "job.log").write_text("written beside the run")
        raise RuntimeError("only 0 of 4 agents registered")
    assert sorted(p.name for p in path.iterdir()) == ["job.log", "notes.txt"]


@pytest.mark.parametrize(
    ("stop", "rounds"), [(KeyboardInterrupt, 0), (RuntimeError, 1)], ids=["interrupted", "recorded"]
)
def test_a_run_that_recorded_a_round_or_was_interrupted_keeps_its_files(
    tmp_path: Path, stop: type[BaseException], rounds: int
) -> None:
    path = tmp_path / "run"
    with pytest.raises(stop), claimed(path, resume=False) as run_dir:
        _start(run_dir, rounds=rounds)
        raise stop()
    assert {"config.json", "metrics.jsonl", "tensorboard"} <= {p.name for p in path.iterdir()}
    assert not (path / LOCK_NAME).exists(), "a server that ends leaves no .lock it made"


def test_refusals_leave_no_lock(tmp_path: Path) -> None:
    path = tmp_path / "run"
    path.mkdir()
    (path / "metrics.jsonl").write_text(json.dumps({"round": 1}) + "\n")
    before = sorted(p.name for p in path.iterdir())
    with pytest.raises(ConfigError, match="holds a run already"):
        RunDirectory.claim(path, resume=False)
    with pytest.raises(ConfigError), claimed(path, resume=True):
        raise ConfigError("rounds", "a resume may keep or raise rounds, never lower them")
    assert sorted(p.name for p in path.iterdir()) == before
    (path / LOCK_NAME).write_text("")  # a lock found there stays
    RunDirectory.claim(path, resume=True).release()
    assert (path / LOCK_NAME).exists()
