"""The pages name only what exists: every repository path, ``fedhpg.*`` name and class a page
puts in backquotes is in the tree, so a rename or a removal that forgets the docs fails here.

Paths (``common/learning/engine/round.py``) must exist from the repository root; dotted names
(``fedhpg.server.commands.api.run``) must import (a module, or an attribute of one); a backquoted
class name (``RoundResult``, ``Strategy.aggregate``) must be defined in the package, its tests
or its benchmarks. Names that belong to other projects or to examples are listed below, each
with where it comes from.
"""

from __future__ import annotations

import importlib
import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [*sorted((ROOT / "docs").glob("**/*.md")), ROOT / "README.md", ROOT / "BENCHMARKS.md"]
SOURCES = ("agent", "common", "envs", "server", "tests", "benchmarks")

NOT_OURS = {
    "DIR/env/mine.yaml": "an example of a user's own config folder",
    "checkpoints/privacy-journal.json": "a file of a run directory",
    "codes/run.py": "FedPG-BR's own code, the reference run",
    "EventFileWriter": "tensorboard's event writer",
    "KillWait": "a SLURM setting",
    "fedhpg.env_families": "an entry-point group, not a module",
    "fedhpg.timeline": "a logger name",
    "fedhpg.py": "the FedHPG algorithm's file, common/learning/algorithms/fedhpg.py",
}
"""Backquoted names that are not this package's modules, files or classes."""

CODE = re.compile(r"`([^`\n]+)`")
PATH = re.compile(r"[\w.-]+(?:/[\w.-]+)+\.(?:py|yaml|sh|toml|md|json|cfg)")
DOTTED = re.compile(r"fedhpg(?:\.\w+)+")
CLASS = re.compile(r"([A-Z][a-z0-9]+(?:[A-Z][a-z0-9]*)+)(?:\.\w+)?")


def _names(pages: list[Path]) -> list[tuple[str, str, str]]:
    """(kind, name, page) of every backquoted path, dotted name and class name."""
    found = []
    for page in pages:
        for match in CODE.finditer(page.read_text(encoding="utf-8")):
            text = match.group(1).strip()
            for kind, pattern in (("path", PATH), ("dotted", DOTTED), ("class", CLASS)):
                whole = pattern.fullmatch(text)
                if whole is not None:
                    name = whole.group(1) if kind == "class" else text
                    if name not in NOT_OURS:
                        found.append((kind, name, page.name))
                    break
    return sorted(set(found))


def _missing(names: list[tuple[str, str, str]]) -> list[str]:
    return [
        f"{page}: `{name}`"
        for kind, name, page in names
        if (kind == "path" and not (ROOT / name).exists())
        or (kind == "dotted" and not _imports(name))
        or (kind == "class" and name not in _defined())
    ]


@cache
def _defined() -> frozenset[str]:
    """Every class and module-level name defined in the tree's Python sources."""
    pattern = re.compile(r"^\s*(?:class\s+(\w+)|(\w+)\s*(?::[^=\n]+)?=)", re.MULTILINE)
    names: set[str] = set()
    for folder in SOURCES:
        for source in (ROOT / folder).glob("**/*.py"):
            for match in pattern.finditer(source.read_text(encoding="utf-8")):
                names.add(match.group(1) or match.group(2))
    return frozenset(names)


def _imports(dotted: str) -> bool:
    parts = dotted.split(".")
    for split in range(len(parts), 0, -1):
        try:
            value: object = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        for attribute in parts[split:]:
            if not hasattr(value, attribute):
                return False
            value = getattr(value, attribute)
        return True
    return False


def test_the_pages_name_paths_modules_and_classes() -> None:
    names = _names(PAGES)
    assert {kind for kind, _, _ in names} == {"path", "dotted", "class"}
    missing = _missing(names)
    assert not missing, "names the docs give that the tree does not have:\n" + "\n".join(missing)


@pytest.mark.parametrize(
    "text",
    ["`common/no_such_module.py`", "`fedhpg.common.records.types.AgentUpdate`", "`LocalResult`"],
)
def test_a_removed_name_is_caught(text: str, tmp_path: Path) -> None:
    """The check finds a name that is gone (here: ones the round result replaced)."""
    page = tmp_path / "page.md"
    page.write_text(
        f"See {text}, beside `common/records/types.py` and `RoundResult`.\n", encoding="utf-8"
    )
    assert _missing(_names([page])) == [f"page.md: {text}"]
