"""benchmarks.kernels_ab loads a commit's compiled engine beside this tree's: the commit's
``compiled.py`` must be bound to the commit's own ``kernels.py``, or the comparison would
measure this tree against itself. (Loading compiles nothing: numba compiles on first call.)"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from benchmarks import kernels_ab
from fedhpg.common.batched import compiled, kernels

ROOT = Path(__file__).resolve().parents[1]


def _in_git_checkout() -> bool:
    inside = subprocess.run(["git", "rev-parse", "--is-inside-work-tree"], cwd=ROOT,
                            capture_output=True, text=True)  # fmt: skip
    return inside.returncode == 0 and inside.stdout.strip() == "true"


pytestmark = pytest.mark.skipif(not _in_git_checkout(), reason="needs the project's git history")


def test_the_commits_engine_is_bound_to_the_commits_kernels() -> None:
    module = kernels_ab.engine_module("HEAD")
    assert module is not compiled and module.kernels is not kernels
    assert module.CompiledFedHPG is not compiled.CompiledFedHPG
    shown = subprocess.run(["git", "show", "HEAD:common/batched/kernels.py"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout  # fmt: skip
    assert Path(module.kernels.__file__).read_text() == shown
    assert Path(module.__file__).parent == Path(module.kernels.__file__).parent


def test_an_unknown_revision_is_a_one_line_error() -> None:
    with pytest.raises(
        SystemExit, match=r"^kernels_ab: no common/batched/\w+\.py at 'no-such-rev'"
    ):
        kernels_ab.engine_module("no-such-rev")
