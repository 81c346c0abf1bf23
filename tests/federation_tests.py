"""Which tests start federations, read from their source without importing it.

A test module that starts federations (tests/procs.py's servers and agents, the launcher,
``api.run(..., distributed=True)``, submitit, multiprocessing) usually holds in-process tests
too: config checks, pure functions, console scripts' one-line errors. tests/conftest.py runs
the tests that start federations one after another on one pytest-xdist worker and spreads the
rest; this module tells the two apart per test. A test starts federations when its function,
the module-level helpers, fixtures and constants it names (transitively) or its class use one
of those means, or build a string that runs a federation's console script or code that does.
In a module that names none of those means, its console scripts' quick runs (a mistake's one
line, a round on the counted clock) are spread, and only a long-tier (``slow``) test that runs
a federation's console script counts. A test that takes a fixture wider than a test (module
or session scope) in a module that starts federations runs with them too, so that the fixture
is built once, on one worker. The reading is conservative: a test that names such a
helper counts even if it only reads a constant from it.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

STARTS_FEDERATIONS = re.compile(
    r"^from procs |^import procs\b|fedhpg\.server\.launcher|\bsubmitit\b|\bmultiprocessing\b"
    r"|\bProcess\(|distributed=True",
    re.MULTILINE,
)
"""What a test module that starts federations uses somewhere in its text."""

FEDERATION_MODULES = ("procs", "fedhpg.server.commands.launcher", "multiprocessing", "submitit")
"""Modules whose names, in a test's code, mean it may start processes."""

BESIDE_THE_TEST = ("Process", "Popen")
"""Processes that run beside the test (a server, an agent, a CPU hog) rather than to their exit
before it goes on."""

IN_A_STRING = re.compile(
    r"\bfedhpg-(run|server|agent|cluster)\b|fedhpg\.server\.launcher|\bsubmitit\b"
    r"|\bmultiprocessing\b|distributed=True"
)
"""What, in a string a test builds (a command line, code run by another interpreter), means it
may start federations."""


@dataclass(frozen=True)
class ModuleSource:
    """A test module: whether its text mentions a means of starting federations, its
    top-level definitions by name, the names it binds by importing one of
    :data:`FEDERATION_MODULES`, its autouse fixtures and its fixtures wider than a test
    (module, package or session scope)."""

    mentions_federations: bool
    definitions: dict[str, ast.AST]
    federation_names: frozenset[str]
    autouse: tuple[str, ...]
    shared: frozenset[str]


def _is_federation_module(name: str | None) -> bool:
    return name is not None and any(
        name == m or name.startswith(m + ".") for m in FEDERATION_MODULES
    )


def _bound_names(node: ast.Import | ast.ImportFrom) -> Iterator[str]:
    if isinstance(node, ast.ImportFrom):
        if _is_federation_module(node.module):
            yield from (alias.asname or alias.name for alias in node.names)
        return
    for alias in node.names:
        if _is_federation_module(alias.name):
            yield alias.asname or alias.name.split(".")[0]


def _is_autouse_fixture(node: ast.AST) -> bool:
    if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
        return False
    return any(
        isinstance(kw, ast.keyword) and kw.arg == "autouse"
        for deco in node.decorator_list
        if isinstance(deco, ast.Call)
        for kw in deco.keywords
    )


def _is_shared_fixture(node: ast.AST) -> bool:
    if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
        return False
    return any(
        kw.arg == "scope"
        and not (isinstance(kw.value, ast.Constant) and kw.value.value in (None, "function"))
        for deco in node.decorator_list
        if isinstance(deco, ast.Call)
        for kw in deco.keywords
    )


@cache
def module_source(path: Path) -> ModuleSource:
    """The definitions of the test module at ``path``."""
    text = path.read_text(encoding="utf-8")
    tree = ast.parse(text, filename=str(path))
    definitions: dict[str, ast.AST] = {}
    federation_names: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            definitions[node.name] = node
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                for name in ast.walk(target):
                    if isinstance(name, ast.Name):
                        definitions[name.id] = node
        elif isinstance(node, ast.Import | ast.ImportFrom):
            federation_names.update(_bound_names(node))
    autouse = tuple(name for name, node in definitions.items() if _is_autouse_fixture(node))
    shared = frozenset(name for name, node in definitions.items() if _is_shared_fixture(node))
    return ModuleSource(
        bool(STARTS_FEDERATIONS.search(text)),
        definitions,
        frozenset(federation_names),
        autouse,
        shared,
    )


def _marked(node: ast.AST | None, mark: str) -> bool:
    decorators = getattr(node, "decorator_list", [])
    return any(
        isinstance(sub, ast.Attribute) and sub.attr == mark
        for deco in decorators
        for sub in ast.walk(deco)
    )


def _marked_slow(node: ast.AST) -> bool:
    return _marked(node, "slow")


def _uses_federations(node: ast.AST, module: ModuleSource, seen: set[str]) -> bool:
    """Whether ``node`` or a top-level definition it names (a helper, a fixture it takes as
    an argument, a constant) uses a means of starting processes, or takes a fixture wider than
    a test."""
    named: list[str] = []
    other_scripts = {  # BIN / "fedhpg-keys": a console script that starts no federation
        id(sub.left)
        for sub in ast.walk(node)
        if isinstance(sub, ast.BinOp)
        and isinstance(sub.op, ast.Div)
        and isinstance(sub.right, ast.Constant)
        and isinstance(sub.right.value, str)
        and not IN_A_STRING.search(sub.right.value)
    }
    for sub in ast.walk(node):
        if isinstance(sub, ast.Import | ast.ImportFrom) and any(_bound_names(sub)):
            return True
        if (
            isinstance(sub, ast.keyword)
            and sub.arg == "distributed"
            and not (isinstance(sub.value, ast.Constant) and sub.value.value is False)
        ):
            return True
        if isinstance(sub, ast.Attribute) and sub.attr in BESIDE_THE_TEST:
            return True
        if isinstance(sub, ast.Name) and id(sub) not in other_scripts:
            if sub.id in module.federation_names or sub.id in BESIDE_THE_TEST:
                return True
            named.append(sub.id)
        elif isinstance(sub, ast.arg):  # a fixture taken as an argument
            named.append(sub.arg)
        elif isinstance(sub, ast.Constant) and isinstance(sub.value, str):
            if IN_A_STRING.search(sub.value):
                return True
            named.append(sub.value)  # pytest.mark.usefixtures("name")
    for name in named:
        if name in module.shared:  # built once, on the worker that runs the federations
            return True
        if name in module.definitions and name not in seen:
            seen.add(name)
            if _uses_federations(module.definitions[name], module, seen):
                return True
    return False


def starts_federations(path: Path, nodeid: str) -> bool:
    """Whether the test ``nodeid`` of the module at ``path`` may start federations (a test
    whose function cannot be found counts, as does a module that cannot be read: it fails
    the run here rather than being spread over both workers)."""
    module = module_source(path)
    parts = nodeid.split("::")
    name = parts[1].split("[", 1)[0] if len(parts) > 1 else ""
    node = module.definitions.get(name)
    if not module.mentions_federations:  # a long run of a console script is a federation
        return node is not None and _marked_slow(node) and _uses_federations(node, module, set())
    if node is None:
        return True
    seen = {name}
    if any(_uses_federations(module.definitions[a], module, seen) for a in module.autouse):
        return True
    return _uses_federations(node, module, seen)


def runs_alongside(path: Path, nodeid: str) -> bool:
    """Whether the test ``nodeid`` of the module at ``path`` is marked ``alongside``: it starts
    federations, but only with the defaults' wide margins (every docs page run as printed), so
    each of its cases is a work unit of its own that may run beside the federations' serial
    unit on the other worker (tests/conftest.py)."""
    parts = nodeid.split("::")
    name = parts[1].split("[", 1)[0] if len(parts) > 1 else ""
    return _marked(module_source(path).definitions.get(name), "alongside")
