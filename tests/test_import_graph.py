"""The package's import graph: no module imports itself back, at run time or for type checking,
and a module imports inside a function only what a named reason keeps out of its import.

The graph is grimp's (the library under import-linter, ``make contracts``), built over the
package laid out under its import name, as ``make contracts`` lays it out.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("agent", "common", "envs", "server")

OPTIONAL_DEPENDENCIES = {
    "ray": "fedhpg-cluster cluster=ray alone (the ray extra)",
    "submitit": "fedhpg-cluster's local and Slurm engines alone (the cluster extra)",
    "wandb": "server.wandb=true alone (the wandb extra)",
    "tensorboard": "server.tensorboard alone (the tensorboard extra)",
    "google_crc32c": "server.tensorboard's record checksums alone (the tensorboard extra)",
    "cryptography": "privacy=secagg alone (the privacy extra)",
    "dp_accounting": "privacy=dp alone (the privacy extra)",
    "scipy": "the secure-aggregation graph's bound alone (it comes with the privacy extra)",
    "mujoco": "the MuJoCo families alone (the envs extra)",
    "gymnasium.envs.mujoco": "the MuJoCo families alone (the envs extra)",
    "gymnasium.wrappers": "fedhpg-record's RecordVideo alone (moviepy: the video extra)",
    "matplotlib": "fedhpg-plot's figures alone: about half a second to import",
    "hydra": "commands that read a command line alone: the library and the agents never load it",
    "omegaconf": "commands that read a command line alone (Hydra's configs)",
    "fedhpg.common.learning.batched.backend": "numba's import and its kernels: runs on the "
    "compiled backend alone",
}
"""What a module may import inside a function (a module or a package and what is under it),
and why its import waits for the call."""

STARTS_WITHOUT_TORCH = {
    "fedhpg.server.commands.cluster.main": "fedhpg-cluster answers --help and checks keys before "
    "torch loads",
    "fedhpg.server.commands.plot": "fedhpg-plot reads metrics files; torch only to rebuild a "
    "variant",
    "fedhpg.server.commands.record": "fedhpg-record answers a usage error before torch loads",
    "fedhpg.common.learning.engine.devices": "the launcher checks a device before it forks: no "
    "torch, no CUDA in the parent",
    "fedhpg.common.runtime.cli": "every entry point answers --help, --version and a mistyped "
    "key before torch, zmq or Hydra loads",
    "fedhpg.common.runtime.composition": "composing a config loads Hydra, checking it the "
    "registries' plugins: only when a command composes",
    "fedhpg.server.commands.launcher": "fedhpg-run checks the whole config and the run directory "
    "before it loads torch, compiles the kernels or forks the agents",
}
"""Modules that import without torch (checked below): they may defer torch and the modules
that bring it."""


def _edges(layout: Path, *, type_checking: bool) -> dict[str, list[str]]:
    """fedhpg's modules and the fedhpg modules each imports, from grimp in a fresh process
    (this one has imported the installed package, which grimp would read instead)."""
    script = (
        "import json, sys, grimp\n"
        f"sys.path.insert(0, {str(layout)!r})\n"
        f"graph = grimp.build_graph('fedhpg', exclude_type_checking_imports={not type_checking},"
        " cache_dir=None)\n"
        "print(json.dumps({m: sorted(i for i in graph.find_modules_directly_imported_by(m)"
        " if i.startswith('fedhpg')) for m in graph.modules}))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=layout, capture_output=True, text=True, check=True
    )
    edges: dict[str, list[str]] = json.loads(out.stdout)
    return edges


@pytest.fixture(scope="module")
def layout(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package's folders under ``fedhpg/``, without fedhpg's own ``__init__``."""
    root = tmp_path_factory.mktemp("layout")
    (root / "fedhpg").mkdir()
    for name in PACKAGES:
        (root / "fedhpg" / name).symlink_to(ROOT / name)
    return root


def cycles(edges: Mapping[str, list[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (and modules importing
    themselves), each sorted (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for imported in edges.get(module, []):
            if imported not in index:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], index[imported])
        if low[module] == index[module]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == module:
                    break
            if len(component) > 1 or module in edges.get(module, []):
                found.append(sorted(component))

    for module in sorted(edges):
        if module not in index:
            visit(module)
    return sorted(found)


def test_cycles_finds_a_cycle_and_only_the_cycle() -> None:
    edges = {"a": ["b"], "b": ["c", "d"], "c": ["a"], "d": [], "e": ["e"]}
    assert cycles(edges) == [["a", "b", "c"], ["e"]]


@pytest.mark.parametrize("type_checking", [False, True], ids=["run-time", "type-checking"])
def test_no_module_imports_itself_back(layout: Path, type_checking: bool) -> None:
    edges = _edges(layout, type_checking=type_checking)
    assert "fedhpg.common.learning.engine.engine" in edges  # the whole package was read
    assert cycles(edges) == []


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(("fedhpg", *(parts[:-1] if parts[-1] == "__init__" else parts)))


def deferred_imports(source: str, package: str) -> Iterator[tuple[int, str]]:
    """(line, imported module) of every import inside a function of ``source``, a module of
    ``package`` (against which relative imports resolve)."""
    tree = ast.parse(source)
    seen: set[int] = set()
    for function in ast.walk(tree):
        if not isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(function):
            if id(node) in seen:
                continue
            seen.add(id(node))
            if isinstance(node, ast.Import):
                for alias in node.names:
                    yield node.lineno, alias.name
            elif isinstance(node, ast.ImportFrom):
                base = package.rsplit(".", node.level - 1)[0] if node.level else ""
                name = ".".join(p for p in (base, node.module or "") if p)
                yield node.lineno, name


def _allowed(importer: str, imported: str) -> bool:
    def under(name: str, parent: str) -> bool:
        return name == parent or name.startswith(parent + ".")

    if any(under(imported, name) for name in OPTIONAL_DEPENDENCIES):
        return True
    return importer in STARTS_WITHOUT_TORCH


def package_files() -> list[Path]:
    return sorted(p for name in PACKAGES for p in (ROOT / name).rglob("*.py"))


def test_deferred_imports_only_for_a_named_reason() -> None:
    unexplained: dict[str, list[str]] = {}
    for path in package_files():
        relative = path.relative_to(ROOT).as_posix()
        importer = _module_name(path)
        package = importer if path.name == "__init__.py" else importer.rpartition(".")[0]
        for line, imported in deferred_imports(path.read_text(), package):
            if not _allowed(importer, imported):
                unexplained.setdefault(relative, []).append(f"{line}: {imported}")
    assert unexplained == {}, (
        "import these at module level (or name the reason in OPTIONAL_DEPENDENCIES): "
        + json.dumps(unexplained, indent=1)
    )


def test_the_counter_sees_nested_and_relative_imports_and_skips_module_level_ones() -> None:
    source = (
        "import torch\n"
        "if torch:\n"
        "    import numpy\n"
        "def f():\n"
        "    import ray\n"
        "    def g():\n"
        "        from . import sibling\n"
        "        from ..other import name\n"
        "    return g\n"
        "class C:\n"
        "    async def h(self):\n"
        "        import wandb.sdk\n"
    )
    assert list(deferred_imports(source, "fedhpg.common.sub")) == [
        (5, "ray"),
        (7, "fedhpg.common.sub"),
        (8, "fedhpg.common.other"),
        (12, "wandb.sdk"),
    ]


@pytest.mark.parametrize("module", sorted(STARTS_WITHOUT_TORCH))
def test_a_module_that_defers_torch_imports_without_it(module: str) -> None:
    script = f"import sys, {module}\nprint('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
