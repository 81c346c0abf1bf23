"""benchmarks.engine_ab and benchmarks.processes_ab run a commit's package beside this tree's:
the folder put on the worker's path must hold that commit's files (or the comparison would
measure this tree against itself), and a revision the clone does not have is a one-line
error."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import engine_ab

ROOT = Path(__file__).resolve().parents[1]


def _in_git_checkout() -> bool:
    inside = subprocess.run(["git", "rev-parse", "--is-inside-work-tree"], cwd=ROOT,
                            capture_output=True, text=True)  # fmt: skip
    return inside.returncode == 0 and inside.stdout.strip() == "true"


pytestmark = pytest.mark.skipif(not _in_git_checkout(), reason="needs the project's git history")


def test_the_folder_holds_the_commits_package() -> None:
    folder = engine_ab.checkout("HEAD")
    for path in (
        "common/learning/group.py",
        "common/learning/engine/engine.py",
        "common/learning/batched/kernels.py",
    ):
        shown = subprocess.run(["git", "show", f"HEAD:{path}"], cwd=ROOT, capture_output=True,
                               text=True, check=True).stdout  # fmt: skip
        assert (folder / "fedhpg" / path).read_text() == shown
    found = "import importlib.util as u; print(u.find_spec('fedhpg.common.records.limits').origin)"
    worker = subprocess.run([sys.executable, "-c", found], env={"PYTHONPATH": str(folder)},
                            capture_output=True, text=True, cwd=folder)  # fmt: skip
    assert worker.stdout.strip() == str(folder / "fedhpg" / "common" / "records" / "limits.py"), (
        worker.stderr
    )


def test_an_unknown_revision_is_a_one_line_error() -> None:
    with pytest.raises(SystemExit, match=r"^engine_ab: no commit 'no-such-rev' in this clone"):
        engine_ab.checkout("no-such-rev")


def test_the_commits_worker_imports_the_commits_package(monkeypatch: pytest.MonkeyPatch) -> None:
    """A caller whose path holds this repository (its ``fedhpg/__init__.py`` a regular
    package) must not make the commit's worker import this tree."""
    folder = engine_ab.checkout("HEAD")
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    side = engine_ab.Side("HEAD's", folder, engine_ab.Setup(agents=1))
    try:
        assert Path(side.ready["package"]).parents[0] == folder
    finally:
        side.close()


def test_a_worker_that_imports_another_package_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"^engine_ab: the empty's worker imported .*, not the "):
        engine_ab.Side("empty's", tmp_path, engine_ab.Setup(agents=1))


def test_the_commits_federation_starts_the_commits_package(monkeypatch: pytest.MonkeyPatch) -> None:
    """benchmarks.processes_ab and benchmarks.scale start a commit's own fedhpg-run from this
    repository's root, where ``python -c`` would put this tree's package first: the check
    behind it passes."""
    monkeypatch.chdir(ROOT)
    tree = engine_ab.baseline_tree("HEAD")
    assert tree.env == {"PYTHONPATH": str(engine_ab.checkout("HEAD"))}
    assert tree.command is not None and tree.command[1] == "-P"


def test_a_federations_round_cpu_is_split_by_process_and_thread() -> None:
    """processes_ab reads where a round's CPU time went: the server, the agents' socket
    threads, their job threads and ZeroMQ's: those that work in a real federation's rounds
    are found working."""
    from benchmarks import processes_ab

    run = processes_ab.federation(engine_ab.THIS_TREE, rounds=4, agents=3)
    assert set(run.cpu_ms) == set(processes_ab.PARTS)
    assert run.cpu_ms["server"] > 0 and run.cpu_ms["main"] > 0 and run.cpu_ms["work"] > 0
    assert run.steps_per_s > 0 and run.peak_pss_mib > 0
