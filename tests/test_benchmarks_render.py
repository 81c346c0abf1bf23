"""BENCHMARKS.md is the rendering of the result files (``python -m benchmarks.render``): the
committed page equals it, a malformed result is one line and exit 2, and a result is marked
stale once a later commit changes the code it measures (in a scratch repository)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from benchmarks import render
from benchmarks.results_file import ROOT, TABLES, Table, load, refresh, write


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false", *args],
        cwd=repo,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()


TABLE: Table = {"columns": ["K", "s"], "rows": [["10", "1.5"]], "summary": "Fast enough."}


def _result(folder: Path, commit: str, measures: list[str]) -> None:
    write(
        "tiny",
        title="Tiny",
        order=1,
        command="python -m benchmarks.tiny",
        measures=measures,
        tables=[TABLE],
        date="2026-01-01",
        commit_hash=commit,
        machine_name="a test machine",
        folder=folder,
    )


@pytest.fixture
def repo(tmp_path: Path) -> Path:
    """A scratch repository with measured code (``code/``) and code beside it (``other/``)."""
    root = tmp_path / "repo"
    for name in ("code", "other"):
        (root / name).mkdir(parents=True)
        (root / name / "x.py").write_text("x = 1\n")
    _git(root, "init", "-q")
    _git(root, "add", ".")
    _git(root, "commit", "-qm", "first")
    return root


def test_the_committed_page_is_the_rendering() -> None:
    rendered = render.render(TABLES, ROOT)
    assert (ROOT / "BENCHMARKS.md").read_text() == rendered, (
        "BENCHMARKS.md is not current: run python -m benchmarks.render"
    )


def test_every_section_names_its_command_machine_date_and_commit() -> None:
    for result in render.load_all(TABLES):
        text = render.section(result, stale=False)
        assert f"`{result['command']}`" in text
        assert f"Measured {result['date']} at commit {result['commit']} on " in text
        assert result["machine"] in text


def test_stale_once_a_later_commit_changes_the_measured_code(repo: Path, tmp_path: Path) -> None:
    measured_at = _git(repo, "rev-parse", "--short", "HEAD")
    results = tmp_path / "results"
    _result(results, measured_at, ["code"])
    assert "**Stale**" not in render.render(results, repo)

    (repo / "other" / "x.py").write_text("x = 2\n")
    _git(repo, "commit", "-qam", "elsewhere")
    assert "**Stale**" not in render.render(results, repo)

    (repo / "code" / "x.py").write_text("x = 3\n")
    uncommitted = render.render(results, repo)
    assert "**Stale**: the code it measures (`code`)" in uncommitted
    _git(repo, "commit", "-qam", "measured code changed")
    assert render.render(results, repo) == uncommitted

    _result(results, _git(repo, "rev-parse", "--short", "HEAD"), ["code"])
    assert "**Stale**" not in render.render(results, repo)


def test_check_gives_a_diff_and_exit_1(
    repo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"
    _result(results, _git(repo, "rev-parse", "--short", "HEAD"), ["code"])
    page = tmp_path / "BENCHMARKS.md"
    args = ["--results", str(results), "--root", str(repo), "--output", str(page)]
    assert render.main(args) == 0
    assert render.main([*args, "--check"]) == 0
    page.write_text(page.read_text().replace("1.5", "1.4"))
    capsys.readouterr()
    assert render.main([*args, "--check"]) == 1
    out = capsys.readouterr().out
    assert "-| 10 | 1.4 |" in out and "+| 10 | 1.5 |" in out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "not JSON"),
        (json.dumps({"title": "x"}), "no 'order'"),
        ("KEEP", "row 1 does not have 2 cells"),
    ],
)
def test_a_malformed_result_is_one_line_and_exit_2(
    repo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, message: str
) -> None:
    results = tmp_path / "results"
    _result(results, _git(repo, "rev-parse", "--short", "HEAD"), ["code"])
    path = results / "tiny.json"
    if content == "KEEP":
        found = json.loads(path.read_text())
        found["tables"][0]["rows"] = [["only one cell"]]
        content = json.dumps(found)
    path.write_text(content)
    page = tmp_path / "BENCHMARKS.md"
    args = ["--results", str(results), "--root", str(repo), "--output", str(page), "--check"]
    assert render.main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "tiny.json" in err
    assert not page.exists()


def test_a_commit_missing_from_the_history_is_one_line_and_exit_2(
    repo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"
    _result(results, "0123abc", ["code"])
    args = ["--results", str(results), "--root", str(repo), "--output", str(tmp_path / "B.md")]
    assert render.main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0123abc is not in the history" in err


@pytest.mark.parametrize("marked", [True, False])
def test_a_check_without_the_history_keeps_the_pages_stale_marks(
    repo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], marked: bool
) -> None:
    """A shallow clone lacks the result's commit: ``--check`` still compares every table, takes
    the stale mark as the page has it, and says so in one line."""
    results = tmp_path / "results"
    _result(results, "0123abc", ["code"])
    page = tmp_path / "B.md"
    args = ["--results", str(results), "--root", str(repo), "--output", str(page)]
    sections = render.load_all(results)
    page.write_text("\n".join([render.INTRO, render.section(sections[0], marked)]).rstrip() + "\n")
    assert render.main([*args, "--check"]) == 0
    assert "stale mark not checked" in capsys.readouterr().err
    page.write_text(page.read_text().replace("1.5", "1.4"))
    assert render.main([*args, "--check"]) == 1


def test_a_measured_path_missing_from_the_repository_is_one_line_and_exit_2(
    repo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"
    _result(results, _git(repo, "rev-parse", "--short", "HEAD"), ["code", "cod"])
    args = ["--results", str(results), "--root", str(repo), "--output", str(tmp_path / "B.md")]
    assert render.main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cod, a measured path, is not in the repository" in err


def test_a_refreshed_result_keeps_its_description_and_takes_the_new_stamps(tmp_path: Path) -> None:
    write(
        "tiny",
        title="Tiny",
        order=1,
        command="python -m benchmarks.tiny",
        measures=["code"],
        setup="What was run.",
        tables=[{**TABLE, "figure": {"path": "docs/figures/tiny.png", "caption": "a curve"}}],
        date="2026-01-01",
        commit_hash="abc1234",
        machine_name="an old machine",
        folder=tmp_path,
    )
    new: Table = {"columns": ["K", "s"], "rows": [["10", "1.2"]], "summary": "Faster."}
    refresh("tiny", [new], "python -m benchmarks.tiny --rounds 3", folder=tmp_path)
    result = load(tmp_path / "tiny.json")
    assert (result["title"], result["measures"], result.get("setup")) == (
        "Tiny",
        ["code"],
        "What was run.",
    )
    assert result["command"] == "python -m benchmarks.tiny --rounds 3"
    assert result["tables"][0]["rows"] == [["10", "1.2"]]
    assert result["tables"][0]["figure"]["path"] == "docs/figures/tiny.png"
    assert (result["date"], result["commit"], result["machine"]) != (
        "2026-01-01",
        "abc1234",
        "an old machine",
    )


def test_a_table_measured_again_to_the_same_rows_keeps_its_reviewed_summary(
    tmp_path: Path,
) -> None:
    """A re-run whose table comes out the same (a learning result after a change that keeps
    every float) keeps the summary written for those numbers; one whose rows moved takes the
    script's."""
    reviewed: Table = {"columns": ["K", "s"], "rows": [["10", "1.5"]], "summary": "Reviewed."}
    other: Table = {"columns": ["x"], "rows": [["1"]], "summary": "Also reviewed."}
    stamps = {"date": "2026-01-01", "commit_hash": "abc1234", "machine_name": "a machine"}
    write("tiny", title="Tiny", order=1, command="python -m benchmarks.tiny", measures=["code"],
          tables=[reviewed, other], folder=tmp_path, **stamps)  # fmt: skip
    same: Table = {**reviewed, "summary": "Generic."}
    moved: Table = {**other, "rows": [["2"]], "summary": "Generic too."}
    refresh("tiny", [same, moved], "python -m benchmarks.tiny", folder=tmp_path)
    tables = load(tmp_path / "tiny.json")["tables"]
    assert [table["summary"] for table in tables] == ["Reviewed.", "Generic too."]
