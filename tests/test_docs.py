"""Every code block of the README and the guides (docs/*.md) runs as printed.

A page's blocks run in order in one fresh working directory (with the repository's ``docs/``
linked in, for the example traces) and the virtual environment's commands first on PATH:
``bash`` blocks as a script that stops at the first failing command, ``python`` blocks in a
fresh interpreter, ``yaml`` and ``toml`` blocks parsed. A ``python`` block right after
``<!-- file: NAME -->`` is written to NAME instead (a plugin module the next blocks use). A
block that cannot run here is marked right before it, ``<!-- not run: why -->``, and the
reason must be given. ``text`` blocks are output, and the README's quickstart output is
checked against what the demo prints. Running the pages takes minutes, so it is in the long
tier (``make test-long``); that every block runs or says why not is checked in ``make test``.

A page in :data:`ONE_BLOCK_A_CASE` (its blocks need nothing from each other's runs, only the
files the page wrote before them) runs one block a case, each in a fresh working directory
holding the page's files written before it, so ``make test-long``'s two workers share it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from procs import BIN

ROOT = Path(__file__).parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(
    r"^```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL
)
MARK = re.compile(r"<!--\s*(?P<kind>not run|file):\s*(?P<value>.*?)\s*-->\s*$")
RUN = {"bash", "python"}
PARSED = {"yaml", "toml"}
OUTPUT = {"text"}
BLOCK_TIMEOUT_S = 300
ONE_BLOCK_A_CASE = {"environments.md"}
"""Pages whose blocks each need only the files the page wrote before them: the longest page
(about 2 min on one core) becomes one case a block."""


@dataclass(frozen=True)
class Block:
    page: Path
    line: int
    language: str
    body: str
    mark: tuple[str, str] | None
    """("not run", why) or ("file", name) from the comment right before the block."""

    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    text = page.read_text(encoding="utf-8")
    found = []
    for match in FENCE.finditer(text):
        before = [line for line in text[: match.start()].splitlines() if line.strip()]
        mark = MARK.search(before[-1]) if before else None
        found.append(
            Block(
                page=page,
                line=text.count("\n", 0, match.start()) + 1,
                language=match["lang"],
                body=match["body"],
                mark=(mark["kind"], mark["value"]) if mark else None,
            )
        )
    return found


def test_every_block_is_run_parsed_or_says_why_not() -> None:
    unknown, unexplained = [], []
    for page in PAGES:
        for block in blocks(page):
            if block.language not in RUN | PARSED | OUTPUT:
                unknown.append(f"{block.where()}: ```{block.language}")
            if block.mark and block.mark[0] == "not run" and len(block.mark[1]) < 10:
                unexplained.append(block.where())
    assert not unknown, f"a block of a language nothing runs: {unknown}"
    assert not unexplained, f"'not run' needs its reason: {unexplained}"


def _workdir(tmp_path: Path) -> Path:
    (tmp_path / "docs").symlink_to(ROOT / "docs")
    return tmp_path


def _environment() -> dict[str, str]:
    return {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
        "FEDHPG_LOG_LEVEL": "WARNING",
        "WANDB_MODE": "offline",
        "WANDB_SILENT": "true",
    }


def _run(block: Block, cwd: Path) -> None:
    if block.language == "bash":
        command = ["bash", "-euo", "pipefail", "-c", block.body]
    else:
        command = [sys.executable, "-c", block.body]
    result = subprocess.run(
        command,
        cwd=cwd,
        env=_environment(),
        capture_output=True,
        text=True,
        timeout=BLOCK_TIMEOUT_S,
    )
    assert result.returncode == 0, (
        f"{block.where()} exited {result.returncode}:\n{block.body}\n"
        f"--- stdout\n{result.stdout[-3000:]}\n--- stderr\n{result.stderr[-3000:]}"
    )


def _checked(block: Block) -> bool:
    """Whether the page's test runs or parses ``block`` (a file block is written, not run)."""
    return block.mark is None and block.language in RUN | PARSED


def _page_cases() -> list[Any]:
    """One case a page, or, for a page of :data:`ONE_BLOCK_A_CASE`, one a checked block
    (``environments.md:14``: the block's line)."""
    cases: list[Any] = []
    for page in PAGES:
        if page.name in ONE_BLOCK_A_CASE:
            lines = [b.line for b in blocks(page) if _checked(b)]
            cases += [pytest.param(page, n, id=f"{page.name}:{n}") for n in lines]
        else:
            cases.append(pytest.param(page, None, id=page.name))
    return cases


def test_a_page_run_one_block_a_case_has_a_case_for_every_block_it_checks() -> None:
    """The split drops no block: every run or parsed block of those pages is a case."""
    split = [p for p in PAGES if p.name in ONE_BLOCK_A_CASE]
    assert [p.name for p in split] == sorted(ONE_BLOCK_A_CASE), "a split page is missing"
    cased = {tuple(c.values) for c in _page_cases() if c.values[1] is not None}
    checked = {(p, b.line) for p in split for b in blocks(p) if _checked(b)}
    assert cased == checked and len(checked) > 1


@pytest.mark.slow
@pytest.mark.alongside  # the pages' federations keep the defaults' waits (60 s to register, …)
@pytest.mark.parametrize(("page", "line"), _page_cases())
def test_the_pages_code_runs_as_printed(page: Path, line: int | None, tmp_path: Path) -> None:
    """The page's blocks in order in one working directory; with ``line``, the block there
    alone, after the page's file blocks above it."""
    cwd = _workdir(tmp_path)
    for block in blocks(page):
        if line is not None and block.line > line:
            break
        if block.mark and block.mark[0] == "not run":
            continue
        if block.mark and block.mark[0] == "file":
            (cwd / block.mark[1]).write_text(block.body, encoding="utf-8")
        elif line is not None and block.line != line:
            continue  # another case runs it
        elif block.language in RUN:
            _run(block, cwd)
        elif block.language == "yaml":
            yaml.safe_load(block.body)
        elif block.language == "toml":
            tomllib.loads(block.body)


def _table(text: str) -> list[str]:
    return [
        line.rstrip() for line in text.splitlines() if line.startswith(("agent-", "environment"))
    ]


def test_the_readmes_quickstart_output_is_what_the_demo_prints(tmp_path: Path) -> None:
    """The demo (make demo: fedhpg-run with the defaults) sleeps to emulate its devices; the
    virtual clock computes the same θ̃ without sleeping, so the same table."""
    readme = ROOT / "README.md"
    shown = next(b for b in blocks(readme) if b.language == "text" and "agent-3" in b.body)
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), "agents.virtual_clock=true"],
        cwd=tmp_path,
        env=_environment(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert _table(result.stdout) == _table(shown.body), result.stdout


def _index_modes() -> dict[str, str]:
    """Path → git's file mode (100644, 100755) of every tracked file."""
    listed = subprocess.run(
        ["git", "ls-files", "-s"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout: {listed.stderr.strip()}")
    modes = {}
    for line in listed.stdout.splitlines():
        info, path = line.split("\t", 1)
        modes[path] = info.split()[0]
    return modes


def _invoked_paths(modes: dict[str, str]) -> set[str]:
    """Tracked files a page's bash block runs as commands (``cluster/ray.sh start``, also after
    ``sudo`` and ``NAME=value``)."""
    invoked = set()
    for page in PAGES:
        for block in blocks(page):
            if block.language != "bash":
                continue
            for line in block.body.splitlines():
                words = [w for w in line.split() if not re.fullmatch(r"\w+=\S*", w)]
                if words and words[0] == "sudo":
                    words = words[1:]
                if words and words[0].removeprefix("./") in modes:
                    invoked.add(words[0].removeprefix("./"))
    return invoked


def test_the_shell_scripts_and_the_scripts_the_pages_run_are_executable_in_git() -> None:
    """A checkout gets git's mode: a script committed 100644 is 'Permission denied' when the
    guides run it by its path (``sudo cluster/ray.sh start``)."""
    modes = _index_modes()
    scripts = {p for p in modes if p.startswith(("cluster/", "docker/")) and p.endswith(".sh")}
    invoked = _invoked_paths(modes)
    assert "cluster/ray.sh" in invoked and "cluster/slurm.sh" in invoked, invoked
    not_executable = sorted(p for p in scripts | invoked if modes[p] != "100755")
    assert not not_executable, f"committed without the executable bit: {not_executable}"
