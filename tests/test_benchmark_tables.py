"""Each benchmark script that writes its own table builds, from the data file it stores, the
very table stored in ``benchmarks/results/tables/`` (its columns and rows): a change to a
script that would change its table fails here, before the next measurement would show it."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from benchmarks import engine_ab, learning_long, presets, results_file, thresholds, tuned_presets
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
    "engine_ab": lambda: engine_ab.tables(engine_ab.load()),
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
