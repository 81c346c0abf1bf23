"""``fedhpg-record``: an MP4 of the unified policy in one agent's environment (a real video
of nonzero frames); a bad run directory, agent index or non-rendering family is one line,
exit 2, nothing written."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from fedhpg.server.commands import api
from fedhpg.server.commands.record import main
from tests.procs import BIN, QUIET

pytest.importorskip("moviepy")


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out_dir = tmp_path_factory.mktemp("record") / "run"
    api.run(
        overrides=["env=cartpole", "rounds=1", "eval.episodes=1", "agents.virtual_clock=true"],
        out_dir=out_dir,
    )
    return out_dir


def test_a_cartpole_run_is_recorded_as_an_mp4_of_its_frames(
    cartpole_run: Path, tmp_path: Path
) -> None:
    imageio = pytest.importorskip("imageio")
    out = tmp_path / "agent-1.mp4"
    assert main([str(cartpole_run), "--agent", "1", "--episodes", "2", "--out", str(out)]) == 0
    reader = imageio.get_reader(out)
    frames = [frame for frame in reader]
    reader.close()
    assert len(frames) >= 2  # two episodes of at least one step each
    assert frames[0].ndim == 3 and frames[0].shape[2] == 3 and frames[0].any()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["agent-1.mp4"]  # no temporary left


@pytest.mark.parametrize(
    ("arguments", "says"),
    [
        (["{run}", "--agent", "4"], "--agent must be in [0, 4)"),
        (["{missing}", "--agent", "0"], "is not a run directory"),
        (["{run}", "--agent", "0", "--best"], "checkpoint.keep_best=true"),
        (["{run}", "--agent", "0", "--out", "{tmp}/video.gif"], "--out must name an .mp4"),
    ],
)
def test_a_mistake_is_one_line_and_exit_2(
    cartpole_run: Path, tmp_path: Path, arguments: list[str], says: str
) -> None:
    values = {"run": cartpole_run, "missing": tmp_path / "nothing", "tmp": tmp_path}
    done = subprocess.run(
        [BIN / "fedhpg-record", *(a.format(**values) for a in arguments)],
        env={**os.environ, **QUIET},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and says in done.stderr, done.stderr
    assert list(tmp_path.iterdir()) == []
    assert not list(cartpole_run.glob("*.mp4"))


def test_a_family_without_rgb_frames_is_refused(tmp_path: Path, capsys) -> None:
    out_dir = tmp_path / "grid"
    api.run(overrides=["rounds=1", "eval.episodes=1", "agents.virtual_clock=true"], out_dir=out_dir)
    assert main([str(out_dir), "--agent", "0"]) == 2
    assert "renders no rgb_array frames" in capsys.readouterr().err
    assert not list(out_dir.glob("*.mp4"))
