"""benchmarks/device_learning.py's summary: each path's mean and spread over seeds at each
evaluation, and their difference in units of the pooled spread."""

from __future__ import annotations

import math

import pytest

from benchmarks import device_learning


def _points(returns: list[float]) -> dict[str, list[float]]:
    return {"round": [5.0, 10.0], "trajectories": [80.0, 160.0], "greedy_return": returns}


def test_the_summary_compares_the_paths_against_the_seeds_spread() -> None:
    results = {
        "auto": {0: _points([20.0, 100.0]), 1: _points([30.0, 200.0])},
        "gymnasium": {0: _points([22.0, 150.0]), 1: _points([28.0, 250.0])},
    }
    rows = device_learning.summary(results)
    assert [r["round"] for r in rows] == [5.0, 10.0]
    last = rows[-1]
    assert last["auto_mean"] == 150.0 and last["gymnasium_mean"] == 200.0
    assert last["auto_sd"] == pytest.approx(math.sqrt(5000.0))
    assert last["difference"] == -50.0
    assert last["difference_in_sd"] == pytest.approx(-50.0 / math.sqrt(5000.0))
    table = device_learning.table(rows, 2)
    assert "| 10 | 160.0 | 150.0 ± 70.7 | 200.0 ± 70.7 | -50.0 | -0.71 |" in table
