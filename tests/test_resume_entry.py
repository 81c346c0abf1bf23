"""What ``resume=`` answers before anything starts: a resume its server would refuse is refused
by fedhpg-run's own checks, before the compiled engine is compiled or a process is forked; a
run that stopped at ``eval.stop_at`` is finished, as a complete run is, unless the resume
changes the target."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from fedhpg.common.runtime.cli import compose
from fedhpg.server.commands import api, launcher
from fedhpg.server.commands.server import _main as serve_main

SHORT = ["rounds=2", "eval.every=1", "eval.episodes=2", "agents.virtual_clock=true"]
REACHED = "eval.stop_at=-1000"  # any evaluation reaches it: the run stops at round 1


def _nothing_may_start(monkeypatch: pytest.MonkeyPatch) -> None:
    def started(*_args: object, **_kwargs: object) -> int:
        raise AssertionError("the launch began")

    monkeypatch.setattr(launcher, "prepare_compiled_engine", started)
    monkeypatch.setattr(launcher, "run_federation", started)


def _fedhpg_run(monkeypatch: pytest.MonkeyPatch, *args: str) -> int:
    """fedhpg-run's entry with ``args``, in this process; its exit status."""
    monkeypatch.setattr(sys, "argv", ["fedhpg-run", *args])
    with pytest.raises(SystemExit) as exit_:
        launcher.main()
    return int(exit_.value.code or 0)


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    out_dir = tmp_path / "run"
    api.run(overrides=SHORT, out_dir=out_dir)
    return out_dir


def test_a_resume_that_lowers_rounds_is_refused_before_the_launch(
    run_dir: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _nothing_may_start(monkeypatch)
    assert _fedhpg_run(monkeypatch, f"resume={run_dir}", "rounds=1") == 2
    err = capsys.readouterr().err
    assert err == (
        f"error: rounds: got 1, but the run in {run_dir} has rounds=2 (checkpointed at round 2);"
        " a resume may keep or raise rounds, never lower them\n"
    )


def test_a_resume_without_a_checkpoint_of_its_rounds_is_refused_before_the_launch(
    run_dir: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    shutil.rmtree(run_dir / "checkpoints")
    before = sorted(p.name for p in run_dir.iterdir())
    _nothing_may_start(monkeypatch)
    assert _fedhpg_run(monkeypatch, f"resume={run_dir}", "rounds=4") == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: resume: no valid checkpoint in {run_dir / 'checkpoints'}")
    assert err.count("\n") == 1
    assert sorted(p.name for p in run_dir.iterdir()) == before, "nothing made or removed"


def test_a_run_stopped_at_its_target_is_finished_on_resume(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*SHORT, REACHED], out_dir=out_dir)
    metrics = (out_dir / "metrics.jsonl").read_bytes()
    _nothing_may_start(monkeypatch)
    assert _fedhpg_run(monkeypatch, f"resume={out_dir}") == 0
    assert capsys.readouterr().out == (
        f"{out_dir} stopped early: round 1's evaluation reached eval.stop_at=-1000, nothing to "
        "run (resume with another eval.stop_at, or eval.stop_at=null, to continue it)\n"
    )
    # fedhpg-server says the same
    server_run = compose([f"resume={out_dir}"], resumable=True)
    assert serve_main(server_run) == 0
    assert "stopped early: round 1's evaluation" in capsys.readouterr().out
    assert (out_dir / "metrics.jsonl").read_bytes() == metrics, "nothing ran"


def test_a_resume_that_changes_the_target_continues(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*SHORT, REACHED], out_dir=out_dir)
    launched: list[int] = []

    def federation(run: object, *, port: bool = False) -> int:
        launched.append(1)
        return 0

    monkeypatch.setattr(launcher, "run_federation", federation)
    assert _fedhpg_run(monkeypatch, f"resume={out_dir}", "eval.stop_at=null") == 0
    assert launched == [1]
    resumed = api.run(overrides=[*SHORT, "resume=true", "eval.stop_at=null"], out_dir=out_dir)
    assert [r["round"] for r in resumed.records] == [1, 2], "the rounds after the target ran"
