"""Each benchmark script that writes its own table builds, from the data file it stores, the
very table stored in ``benchmarks/results/tables/`` (its columns and rows): a change to a
script that would change its table fails here, before the next measurement would show it."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable

import pytest

from benchmarks import (
    containers,
    device_tables,
    engine_ab,
    figures,
    learning,
    learning_long,
    presets,
    processes_ab,
    results_file,
    thresholds,
    tuned_presets,
)
from benchmarks.results_file import TABLES, Table


def _presets() -> list[Table]:
    return presets.tables(presets.load(presets.RESULTS))


def _tuned(task_name: str) -> Callable[[], list[Table]]:
    def build() -> list[Table]:
        task = tuned_presets.TASKS[task_name]
        return tuned_presets.result_tables(
            task, tuned_presets.paper_curves(task) + tuned_presets.load(task)
        )

    return build


def _thresholds() -> list[Table]:
    curves = thresholds.load(thresholds.RESULTS, thresholds.CODE_LOGS)
    return thresholds.main_tables(curves, thresholds.stored_rows(curves), thresholds.CODE_LOGS)


def _thresholds_search() -> list[Table]:
    curves = thresholds.load(thresholds.SEARCH_RESULTS, None)
    return thresholds.search_tables(curves, thresholds.stored_rows(curves))


BUILDERS: dict[str, Callable[[], list[Table]]] = {
    "presets": _presets,
    "thresholds": _thresholds,
    "thresholds_search": _thresholds_search,
    "thresholds_wall": lambda: thresholds.wall_tables(
        thresholds.load(thresholds.RESULTS, thresholds.CODE_LOGS)
    ),
    "containers": lambda: containers.tables(json.loads(containers.RESULTS.read_text())),
    **{name: functools.partial(device_tables.stored_tables, name) for name in device_tables.NAMES},
    "engine_ab": lambda: engine_ab.tables(engine_ab.load()),
    "engine_ab_processes": lambda: [processes_ab.table(*processes_ab.load())],
    "figures": lambda: figures.result_tables((figures.FIGURES / "summary.md").read_text()),
    "learning_long": lambda: learning_long.result_tables(learning_long.stored()),
    "tuned_lunarlander": _tuned("lunarlander"),
    "tuned_halfcheetah": _tuned("halfcheetah"),
}


@pytest.fixture(autouse=True)
def _in_the_root(monkeypatch: pytest.MonkeyPatch) -> None:
    """The scripts name their data relative to the repository root, where they are run."""
    monkeypatch.chdir(results_file.ROOT)


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_the_script_builds_the_stored_table(name: str) -> None:
    stored = results_file.load(TABLES / f"{name}.json")["tables"]
    built = BUILDERS[name]()
    assert [(t["columns"], t["rows"]) for t in built] == [(t["columns"], t["rows"]) for t in stored]


@pytest.mark.parametrize("name", sorted(BUILDERS))
def test_the_stored_summary_is_the_scripts(name: str) -> None:
    """The stored summary is the one the script computes from the data (none written by
    hand), as ``--tables-only`` writes it."""
    stored = results_file.load(TABLES / f"{name}.json")["tables"]
    assert [t["summary"] for t in BUILDERS[name]()] == [t["summary"] for t in stored]


@pytest.mark.parametrize("kind", learning.KINDS)
def test_learning_builds_the_stored_columns(kind: str) -> None:
    """benchmarks.learning stores no curves from the run its tables were transcribed from
    (the next run writes ``benchmarks/results/learning_cartpole.json``): its table is checked
    for the stored columns, on made-up curves, one of which never reaches the target."""

    def curve(agents: int, label: str, seed: int, reach: bool) -> learning.Curve:
        returns = [100.0, 480.0 if reach else 200.0]
        return learning.Curve(agents, seed, label, [16.0, 32.0], returns, [1.0, 2.0], 50.0)

    curves = [
        curve(10, "fedhpg K=10", 0, True),
        curve(10, "fedhpg K=10", 1, False),
        curve(1, "fedhpgvr K=1", 0, True),
    ]
    built = learning.tables(kind, curves)
    stored = results_file.load(TABLES / f"learning_{kind}.json")["tables"]
    assert [t["columns"] for t in built] == [t["columns"] for t in stored]
    rows = built[0]["rows"]
    assert [row[1] for row in rows] == ["1/2", "1/1"]
    assert rows[0][2] == "**32** (32, —)" and rows[1][2] == "**32** (32)"
    assert "misses it on 1 of 2 seeds" in built[0]["summary"]
