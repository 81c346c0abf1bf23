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
    scale,
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
    "scale": lambda: [scale.stored_table()],
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


def _case_result(
    key: str, window: str, per_core_steps: float, **figures: float
) -> scale.CaseResult:
    """A made-up result of ``key``: (b) at 1 M steps/s, the whole round at ``per_core_steps``
    per core of the hosts it uses."""
    case = scale.CASES[key]
    cores = min(-(-case.agents // case.per_host), scale.CORES)
    given = {"start_to_round_1_s": 3.0, "peak_pss_mib": 900.0, "sampling": 0.5e6} | figures
    return scale.CaseResult(
        case=case,
        start_to_round_1_s=given["start_to_round_1_s"],
        peak_pss_mib=given["peak_pss_mib"],
        participants=case.per_round or case.agents,
        env_steps_per_round=1e4,
        sampling_steps_per_cpu_s=given["sampling"],
        round_steps_per_s=per_core_steps * cores,
        round_time_s=0.1,
        coordination_us_per_agent=given.get("coordination", 30.0),
        copies_per_host=100,
        refs={"a_bare_gym": 2e6, "b_gym_plus_forward": 1e6},
        key=key,
        window=window,
    )


def test_scale_puts_the_commits_runs_beside_this_trees_and_dashes_what_it_did_not_run() -> None:
    this = [
        _case_result("k1000", "2–4", 0.35e6),
        _case_result("k1000", "28–30", 0.5e6),
        _case_result("k1000", "2–30", 0.4e6),
        _case_result("k10000", "2–4", 0.2e6, sampling=0.8e6, peak_pss_mib=600.0),
        _case_result("overhead", "2–4", 0.1e6, coordination=60.0),
    ]
    that = [_case_result("k1000", "2–4", 0.1e6), _case_result("k10000", "2–4", 0.25e6)]
    built = scale.summary_table(this, that, "abc1234")
    assert built["columns"] == ["case", "this tree", "abc1234, same machine", "target"]
    rows = {row[0]: row[1:] for row in built["rows"]}
    assert rows["K = 1,000, whole round per core vs (b), rounds 2–4"] == ["0.35", "0.10", "0.3"]
    assert rows["K = 1,000, rounds 28–30 / 2–30"] == ["0.50 / 0.40", "0.10 / 0.10", ""]
    assert rows["K = 10,000 (1,000 a round), whole round per core"] == ["0.20", "0.25", "0.3"]
    assert rows["peak PSS, K = 1,000 / 10,000 (MiB)"] == ["900 / 600", "900 / 900", "2,048"]
    device = next(cells for label, cells in rows.items() if "torch CartPole" in label)
    assert device == ["— / —", "— / —", ""]
    summary = built["summary"]
    assert summary.startswith("At this tree the whole round per core at K = 1,000 (early rounds)")
    assert "the whole round per core at K = 10,000" in summary.split(";")[1]  # missed: 0.20 < 0.3
    assert "coordination at d ≈ 10⁴" in summary.split(";")[1]  # missed: 60 µs > 50
    assert "At abc1234, on the same machine:" in summary
    assert summary.endswith(
        "this tree ÷ abc1234: 3.50 at K = 1,000 (rounds 2–4) and 0.80 at K = 10,000."
    )


def test_a_thresholds_call_that_runs_nothing_keeps_its_tables_stamps(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every run asked for is stored (as ``benchmarks.learning``'s closing call asks): the
    tables are rebuilt with their measurement's stamps, not stamped with this commit."""
    rebuilt: list[bool] = []

    def refresh(*args: object, **kwargs: object) -> None:
        raise AssertionError("stored runs stamped as measured now")

    monkeypatch.setattr(thresholds.results_file, "refresh", refresh)
    monkeypatch.setattr(thresholds, "write_tables", lambda: rebuilt.append(True))
    monkeypatch.setattr(thresholds, "plot", lambda *args, **kwargs: None)
    monkeypatch.setattr(thresholds, "run_curve", refresh)
    thresholds.main(["--seeds", "0", "1"])
    assert rebuilt == [True]
    assert "| run |" in capsys.readouterr().out
