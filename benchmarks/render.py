"""BENCHMARKS.md, rendered from the result files (``benchmarks/results/tables/*.json``, the
shape of :mod:`benchmarks.results_file`).

    python -m benchmarks.render            # writes BENCHMARKS.md
    python -m benchmarks.render --check    # exit 1 and a unified diff if BENCHMARKS.md differs

Each result becomes one section: its command, the machine, date and commit it was measured
with, its set-up, its tables with their summaries and figures. A result is marked **stale**
when the code it measures changed after it was measured: some commit after the result's
commit touches one of its ``measures`` paths (``git log <commit>..HEAD -- <paths>``), or the
working tree changes one of them against HEAD.

The mark names no commit and no count of commits, only the measured paths, so the rendering
changes exactly when a result turns stale (or is re-measured), not with every commit. Because
uncommitted changes count too, a change to measured code and the re-rendered BENCHMARKS.md go
in the same commit: edit the code, run ``python -m benchmarks.render``, commit both; ``--check``
(run by ``make test``) then holds at that commit and after it, until measured code changes
again.

A result file that does not have the shape is one line and exit 2; so is a result whose commit
is not in this repository's history (a shallow clone: fetch the history first), and one that
measures a path the repository does not have (moved code: update its ``measures``). Only
``--check`` goes on without the history: it checks everything but the stale marks of such
results, and says so.
"""

from __future__ import annotations

import argparse
import difflib
import subprocess
import sys
from pathlib import Path

from benchmarks.results_file import ROOT, TABLES, Result, ResultError, Table, load

OUTPUT = ROOT / "BENCHMARKS.md"

INTRO = """\
# Benchmarks

One section per benchmark: the command that measures it, the machine, date and commit of the
run the figures come from, and its tables. This file is generated: each benchmark's result is a
file in `benchmarks/results/tables/`, and `python -m benchmarks.render` writes this page from
them (`--check` tells whether it is up to date; `make test` runs it). To measure a benchmark
again, run its command from the repository root and render.

**Machines.** Each section names the machine its figures were taken on; tables from different
machines are never mixed. Wall-clock times on a shared machine move by ±10 % from one run to
the next (±30 % on some days), so speed is compared against a baseline measured in the same
run; learning results are counts of trajectories or returns, which do not depend on the
machine. The tests never assert wall-clock times.

**Stale.** A section marked **stale** was measured before the code it measures last changed
(a later commit, or the working tree, changes one of the paths it names): its figures describe
an earlier version of that code. Re-run its command to refresh it. The mark names only those
paths, so this page changes when a result turns stale or is measured again, not with every
commit; a change to measured code is committed together with the page rendered after it.

Why the figures come out as they do is explained in the guide's "How it works", section
"Performance" (`docs/how-it-works.md`).

**Figures** are drawn by `fedhpg.server.commands.plot` (mean over seeds, band = 95 %
percentile-bootstrap interval of that mean, 2,000 resamples); they are in `docs/figures/`
(bench-scale's in `docs/`) with their data in `benchmarks/results/`.
"""


class RenderError(Exception):
    """Something the renderer cannot work around; the message is one line."""


def _git(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    try:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=False)
    except FileNotFoundError:
        raise RenderError("git is not installed; the stale marks need the history") from None


class UnknownCommit(RenderError):
    """The result's commit is not in the history (a shallow clone)."""


def is_stale(root: Path, commit: str, measures: list[str]) -> bool:
    """Whether any of ``measures`` changed after ``commit``, in a later commit or in the
    working tree."""
    known = _git(root, "cat-file", "-e", f"{commit}^{{commit}}")
    if known.returncode != 0:
        raise UnknownCommit(
            f"commit {commit} is not in the history of {root} (a shallow clone? fetch it)"
        )
    tracked = _git(root, "ls-tree", "-r", "--name-only", "HEAD", "--", *measures).stdout.split()
    for path in measures:
        if not any(name == path or name.startswith(path.rstrip("/") + "/") for name in tracked):
            raise RenderError(f"{path}, a measured path, is not in the repository at HEAD")
    later = _git(root, "log", "--format=%h", "-1", f"{commit}..HEAD", "--", *measures)
    if later.returncode != 0:
        raise RenderError(f"git log failed in {root}: {later.stderr.strip().splitlines()[-1]}")
    if later.stdout.strip():
        return True
    return _git(root, "diff", "--quiet", "HEAD", "--", *measures).returncode != 0


def load_all(folder: Path) -> list[Result]:
    """Every result in ``folder``, in their order."""
    paths = sorted(folder.glob("*.json"))
    if not paths:
        raise ResultError(f"{folder}: no result files")
    results = [load(path) for path in paths]
    return sorted(results, key=lambda result: (result["order"], result["title"]))


def _escape(cell: str) -> str:
    return cell.replace("|", "\\|")


def _table(table: Table) -> list[str]:
    lines = []
    if "title" in table:
        lines += [f"**{table['title']}**", ""]
    if "command" in table:
        lines += [f"`{table['command']}`", ""]
    lines.append("| " + " | ".join(map(_escape, table["columns"])) + " |")
    lines.append("|" + "---|" * len(table["columns"]))
    lines += ["| " + " | ".join(map(_escape, row)) + " |" for row in table["rows"]]
    lines += ["", table["summary"], ""]
    if "figure" in table:
        figure = table["figure"]
        if "ref" in figure:
            lines += [
                f"![{figure['caption']}][{figure['ref']}]",
                "",
                f"[{figure['ref']}]: {figure['path']}",
                "",
            ]
        else:
            lines += [f"Figure: `{figure['path']}`: {figure['caption']}", ""]
    return lines


def section(result: Result, stale: bool) -> str:
    """One result as its section of BENCHMARKS.md."""
    lines = [f"## {result['title']}", ""]
    lines += [f"`{result['command']}`", ""]
    lines += [
        f"Measured {result['date']} at commit {result['commit']} on {result['machine']}.",
        "",
    ]
    if stale:
        paths = ", ".join(f"`{path}`" for path in result["measures"])
        lines += [
            f"**Stale**: the code it measures ({paths}) changed after this run; "
            "re-run the command above to refresh it.",
            "",
        ]
    if "setup" in result:
        lines += [result["setup"], ""]
    if "data" in result:
        lines += ["Data: " + ", ".join(f"`{path}`" for path in result["data"]) + ".", ""]
    for table in result["tables"]:
        lines += _table(table)
    return "\n".join(lines)


def render(folder: Path = TABLES, root: Path = ROOT, committed: str | None = None) -> str:
    """BENCHMARKS.md from the results in ``folder``, stale marks against the history of
    ``root``. Given the ``committed`` page (a check), a result whose commit the history lacks
    keeps the mark the page gives it, and a line on stderr says so: a shallow clone checks
    every table but cannot judge staleness."""
    parts = [INTRO]
    for result in load_all(folder):
        for path in result.get("data", []):
            if not (root / path).exists():
                raise RenderError(f"{result['title']}: its data {path} is not in {root}")
        try:
            stale = is_stale(root, result["commit"], result["measures"])
        except UnknownCommit as error:
            if committed is None:
                raise
            print(f"benchmarks.render: stale mark not checked: {error}", file=sys.stderr)
            stale = _marked_stale(committed, result["title"])
        parts.append(section(result, stale))
    return "\n".join(parts).rstrip("\n") + "\n"


def _marked_stale(page: str, title: str) -> bool:
    """Whether ``page``'s section ``title`` carries the stale mark."""
    _, found, rest = page.partition(f"\n## {title}\n")
    return bool(found) and "\n**Stale**: " in rest.split("\n## ", 1)[0]


def check(rendered: str, output: Path) -> str:
    """A unified diff of ``output`` against the rendering; empty when they are equal."""
    try:
        committed = output.read_text()
    except FileNotFoundError:
        committed = ""
    return "".join(
        difflib.unified_diff(
            committed.splitlines(keepends=True),
            rendered.splitlines(keepends=True),
            fromfile=f"{output.name} (as it is)",
            tofile=f"{output.name} (rendered)",
            n=1,
        )
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.render", description=__doc__)
    parser.add_argument(
        "--check", action="store_true", help="exit 1 with a diff if BENCHMARKS.md is not current"
    )
    parser.add_argument("--results", type=Path, default=TABLES, help=argparse.SUPPRESS)
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    parser.add_argument("--output", type=Path, default=OUTPUT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    try:
        committed = args.output.read_text() if args.check and args.output.exists() else None
        rendered = render(args.results, args.root, committed)
    except (ResultError, RenderError) as error:
        print(f"benchmarks.render: {error}", file=sys.stderr)
        return 2
    if args.check:
        diff = check(rendered, args.output)
        if diff:
            shown = diff.splitlines(keepends=True)
            sys.stdout.write("".join(shown[:60]))
            if len(shown) > 60:
                print(f"... {len(shown) - 60} more lines of diff")
            print(
                f"{args.output.name} is not the rendering of the results: "
                "run python -m benchmarks.render",
                file=sys.stderr,
            )
            return 1
        return 0
    args.output.write_text(rendered)
    return 0


if __name__ == "__main__":
    sys.exit(main())
