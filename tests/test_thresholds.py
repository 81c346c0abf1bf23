"""benchmarks.thresholds: FedPG-BR's printed counter converted to trajectories per agent,
checked against a logged run of FedPG-BR's own code; the evaluation grid, "solved" and the
fraction held, on constructed curves; the benchmark's rows as the presets compose."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from benchmarks.thresholds import (
    ROWS,
    Curve,
    code_curve,
    counter_step,
    from_counter,
    on_grid,
    outcome,
    sampled_per_agent,
)
from fedhpg.server.commands.api import resolve_config

LOGGED = Path(__file__).parent / "fedpgbr_code_run"
"""FedPG-BR's code, seed 0, server step 1e-2, to 200 trajectories per agent: the log of
benchmarks/fedpgbr_code.py and the lines its code printed (``Gradient step: …``)."""


def _logged() -> tuple[dict[str, int], list[dict[str, float]], list[int]]:
    lines = [json.loads(line) for line in (LOGGED / "run.jsonl").read_text().splitlines()]
    printed = re.findall(r"Gradient step:\s+(\d+)", (LOGGED / "run.out").read_text())
    return lines[0], lines[1:], [int(p) for p in printed]


def test_fedpgbrs_printed_counter_adds_counter_step_each_round() -> None:
    header, rounds, printed = _logged()
    assert printed == [r["counter"] for r in rounds]
    for before, now, r in zip([0, *printed], printed, rounds, strict=False):
        assert now - before == counter_step(
            r["batch_size"], r["inner_steps"], header["K"], header["b"]
        ), r
    # the run has rounds whose last inner batch was sampled, then aborted and not counted
    assert any(r["inner_batches"] == r["inner_steps"] + 1 for r in rounds)


def test_the_printed_counter_converts_to_trajectories_per_agent() -> None:
    """from_counter(counter) is the trajectories per agent but for b/K per aborted step and
    FedPG-BR's rounding, (K + 1)/(2K) a round at most; counted as printed (×1) or with the
    server's whole b·N_t per agent, the count would be off by far more."""
    header, rounds, printed = _logged()
    agents, mini_batch = header["K"], header["b"]
    curve = code_curve(LOGGED / "run.jsonl")
    exact, aborted = 0.0, 0
    for i, r in enumerate(rounds):
        exact += r["batch_size"] + mini_batch * r["inner_batches"] / agents
        aborted += r["inner_batches"] - r["inner_steps"]
        assert curve.trajectories[i] == pytest.approx(exact)
        gap = curve.trajectories[i] - from_counter(printed[i], agents)
        rounding = (i + 1) * (agents + 1) / (2 * agents)
        assert abs(gap - mini_batch * aborted / agents) <= rounding, (i, gap, aborted)
    assert curve.trajectories[-1] >= 200 and aborted > 0
    assert sampled_per_agent(16, 5) == 18.0


def _curve(trajectories: list[float], returns: list[float]) -> Curve:
    n = len(trajectories)
    return Curve("stable", 0.01, 0, trajectories, returns, list(range(1, n + 1)), [1.0] * n)


def test_the_grid_keeps_the_rounds_that_cross_a_multiple_of_the_interval() -> None:
    # rounds of 18 trajectories per agent: 18, 36, 54, 72 cross 16, 32, 48, 64; 90 crosses 80,
    # 108 crosses 96, 126 crosses 112, 144 crosses 128 and 144 (once)
    curve = _curve([18.0 * k for k in range(1, 9)], [0.0] * 8)
    assert on_grid(curve) == list(range(8))
    # rounds of 12: 12 crosses nothing, 24 crosses 16, 36 crosses 32, 48 lands on 48
    curve = _curve([12.0, 24.0, 36.0, 48.0, 60.0], [0.0] * 5)
    assert on_grid(curve) == [1, 2, 3]
    # B = 2 evaluated every 8 rounds: every evaluation, the budget's off-grid one left out
    curve = _curve([16.0 * k for k in range(1, 63)] + [1000.0], [0.0] * 63)
    assert on_grid(curve) == list(range(62))


def test_solved_needs_every_evaluation_of_the_next_256_trajectories() -> None:
    times = [16.0 * k for k in range(1, 63)] + [1000.0]
    returns = [100.0 if t < 160 else 500.0 for t in times]
    returns[times.index(304.0)] = 470.0  # one dip: 160 is not solved, 320 is
    found = outcome(_curve(times, returns))
    assert (found.first, found.solved) == (160.0, 320.0)
    assert found.held == pytest.approx(52 / 53)  # 160 … 992 on the grid, one below
    assert (found.rounds, found.episodes) == (20, 200)
    # the hold must fit in the budget: a first 475 at 800 is not solved by 1,000
    late = outcome(_curve(times, [500.0 if t >= 800 else 0.0 for t in times]))
    assert (late.first, late.solved, late.held, late.last) == (800.0, None, 1.0, 500.0)


@pytest.mark.parametrize("row", [r for r, spec in ROWS.items() if spec.per_round is not None])
def test_a_fixed_rows_rounds_are_its_trajectories_per_round(row: str) -> None:
    """The evaluation interval is 16 / per_round rounds: per_round must be B·τ of the run."""
    run = resolve_config(overrides=list(ROWS[row].overrides))
    budget = run.agents.budget
    assert budget["batch_size"][0] * budget["local_iters"][0] == ROWS[row].per_round
