"""Theorem 1 as a planner (common/learning/planning.py, fedhpg-plan).

- The search is exact where it says it is: on small boxes its bound equals the minimum over
  every integer (B_k, τ_k) found by brute force through the same eq. 7.
- The plan keeps every agent within the round time it was planned for, both in its own
  arithmetic and in a real counted-clock run of the planned budgets (GridWorld, in process).
- A device whose speed changes (agents.schedule) changes the plan.
- Theorem 2's evaluable shape against the formula written out; fedhpg-plan's output and its
  one-line errors.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys

import pytest

from fedhpg.common.heterogeneity.device import device_for
from fedhpg.common.learning.planning import (
    Constants,
    Limits,
    plan_budgets,
    score_budgets,
    theorem2_shape,
)
from fedhpg.common.runtime.cli import compose
from fedhpg.server.commands import api
from fedhpg.server.commands.plan import (
    horizon_seconds_per_trajectory,
    main,
    observed_seconds_per_trajectory,
    round_overhead_s,
)

COUNTED = ["agents.clock=counted", "agents.virtual_clock=true"]


def _brute_force(constants, seconds, overhead, total_s, limits):
    k = len(seconds)
    per_agent = list(
        itertools.product(
            range(limits.batch_min, limits.batch_max + 1), range(1, limits.local_iters_max + 1)
        )
    )
    best = None
    for choice in itertools.product(per_agent, repeat=k):
        batches = [b for b, _ in choice]
        iters = [t for _, t in choice]
        if (
            max(t * b * c + o for b, t, c, o in zip(batches, iters, seconds, overhead, strict=True))
            > total_s
        ):
            continue
        scored = score_budgets(
            constants=constants,
            seconds_per_trajectory=seconds,
            overhead_s=overhead,
            total_s=total_s,
            batch_sizes=batches,
            local_iters=iters,
        )
        if best is None or scored.bound < best.bound:
            best = scored
    return best


@pytest.mark.parametrize(
    ("gap", "smoothness", "second_moment", "total_s"),
    [
        (1.0, 0.5, 2.0, 3.0),  # τ > 1 costs heterogeneity: τ = 1 wins
        (50.0, 0.05, 0.01, 3.0),  # a large gap, little drift: more local steps pay
        (5.0, 0.2, 0.1, 0.7),  # a tight budget: few rounds
    ],
)
def test_the_search_finds_the_brute_force_minimum(gap, smoothness, second_moment, total_s):
    constants = Constants(
        gap=gap,
        step_size=0.5,
        smoothness=smoothness,
        second_moment=second_moment,
        variances=(1.0, 3.0, 0.5),
    )
    seconds = [0.01, 0.02, 0.04]
    overhead = [0.002, 0.002, 0.005]
    limits = Limits(batch_min=2, batch_max=7, local_iters_max=3)
    plan = plan_budgets(
        constants=constants,
        seconds_per_trajectory=seconds,
        overhead_s=overhead,
        total_s=total_s,
        limits=limits,
    )
    best = _brute_force(constants, seconds, overhead, total_s, limits)
    assert plan.step_size_ok and best.step_size_ok
    assert plan.bound == pytest.approx(best.bound, rel=1e-12)


def test_every_agent_keeps_within_the_planned_round_and_the_total():
    constants = Constants(
        gap=2.0, step_size=0.5, smoothness=0.8, second_moment=1.5, variances=(1.0,) * 4
    )
    seconds = [0.01, 0.01, 0.02, 0.04]
    overhead = [0.001] * 4
    plan = plan_budgets(
        constants=constants, seconds_per_trajectory=seconds, overhead_s=overhead, total_s=30.0
    )
    for b, t, c, o, r in zip(
        plan.batch_sizes, plan.local_iters, seconds, overhead, plan.agent_round_s, strict=True
    ):
        assert t * b * c + o == pytest.approx(r) and r <= plan.round_s
    assert plan.rounds * plan.round_s <= 30.0 < (plan.rounds + 1) * plan.round_s


def test_a_step_size_that_breaks_the_second_condition_lowers_tau():
    # γ L α_B K > 2 (K + τ̄) at τ = 8: the largest-τ plan is refused, a smaller τ kept.
    constants = Constants(
        gap=1e4, step_size=0.9, smoothness=1.0, second_moment=1e-6, variances=(1e-3, 1e-3)
    )
    plan = plan_budgets(
        constants=constants,
        seconds_per_trajectory=[0.01, 0.01],
        overhead_s=[0.0, 0.0],
        total_s=10.0,
        limits=Limits(local_iters_max=8),
    )
    assert plan.step_size_ok
    assert max(plan.local_iters) < 8


def test_no_round_fits_is_an_error():
    constants = Constants(gap=1.0, step_size=0.5, smoothness=1.0, second_moment=1.0, variances=(1,))
    with pytest.raises(ValueError, match="no round"):
        plan_budgets(
            constants=constants, seconds_per_trajectory=[1.0], overhead_s=[0.0], total_s=1.0
        )


def test_a_planned_run_stays_within_its_planned_round_times():
    """The horizon cost is an upper bound on the counted clock: run the plan and read each
    agent's emulated seconds from the round records."""
    overrides = [*COUNTED, "eval.every=100", "eval.episodes=1"]
    run = compose(overrides)
    seconds = horizon_seconds_per_trajectory(run)
    overhead = round_overhead_s(run)
    constants = Constants(
        gap=1.0, step_size=0.5, smoothness=1.0, second_moment=2.0, variances=(1.0,) * 4
    )
    plan = plan_budgets(
        constants=constants,
        seconds_per_trajectory=seconds,
        overhead_s=overhead,
        total_s=1.5,
        limits=Limits(batch_max=12, local_iters_max=2),
    )
    batches = ",".join(map(str, plan.batch_sizes))
    iters = ",".join(map(str, plan.local_iters))
    result = api.run(
        overrides=[
            *overrides,
            f"rounds={min(plan.rounds, 3)}",
            f"agents.budget.batch_size=[{batches}]",
            f"agents.budget.local_iters=[{iters}]",
        ]
    )
    for record in result.records:
        for agent in record["agents"]:
            assert agent["emulated_s"] <= plan.agent_round_s[agent["index"]] * (1 + 1e-9)
            assert agent["emulated_s"] <= plan.round_s * (1 + 1e-9)


def test_a_device_whose_speed_changes_changes_the_plan():
    """agents.schedule=periodic: the speeds of round 1 and of the round a quarter period on
    (sin at its peak) are different devices, and the plan follows them. No env-step throttle,
    so that a trajectory's time is its compute over the speed."""
    schedule = ["agents.schedule=periodic", "agents.schedule_period_rounds=8"]
    run = compose([*COUNTED, *schedule, "agents.step_delays_s=[0.0]"])
    constants = Constants(
        gap=1.0, step_size=0.5, smoothness=1.0, second_moment=2.0, variances=(1.0,) * 4
    )
    overhead = round_overhead_s(run)
    plans = {}
    for round_index in (1, 3):
        seconds = horizon_seconds_per_trajectory(run, round_index)
        plans[round_index] = plan_budgets(
            constants=constants, seconds_per_trajectory=seconds, overhead_s=overhead, total_s=20.0
        )
        for t, b, c, o, r in zip(
            plans[round_index].local_iters,
            plans[round_index].batch_sizes,
            seconds,
            overhead,
            plans[round_index].agent_round_s,
            strict=True,
        ):
            assert t * b * c + o == pytest.approx(r)
            assert r <= plans[round_index].round_s
    # Round 3: every device at 1.5× its speed; per round, the same time buys more trajectories.
    assert plans[3].batch_sizes != plans[1].batch_sizes
    assert plans[3].bound < plans[1].bound


def test_observed_speeds_follow_the_schedule_and_re_make_the_plan():
    """What a planner re-planning every round would see: the seconds per env step observed in
    round 3 are round 1's times speed_1 / speed_3 for every agent (the counted clock prices
    compute over the scheduled speed), and the plan made from them differs."""
    schedule = ["agents.schedule=periodic", "agents.schedule_period_rounds=8"]
    overrides = [*COUNTED, *schedule, "agents.step_delays_s=[0.0]", "eval.every=100"]
    overrides += [
        "eval.episodes=1",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]",
    ]
    result = api.run(overrides=[*overrides, "rounds=3"])
    run = result.config
    by_round = {r["round"]: r for r in result.records}
    step_1 = observed_seconds_per_trajectory(run, [by_round[1]], per="env_steps")
    step_3 = observed_seconds_per_trajectory(run, [by_round[3]], per="env_steps")
    for k in range(run.agents.num_agents):
        device = device_for(run, k)
        assert step_3[k] / step_1[k] == pytest.approx(device.speed_at(1) / device.speed_at(3))
    constants = Constants(
        gap=1.0, step_size=0.5, smoothness=1.0, second_moment=2.0, variances=(1.0,) * 4
    )
    overhead = round_overhead_s(run)
    plans = [
        plan_budgets(
            constants=constants,
            seconds_per_trajectory=observed_seconds_per_trajectory(run, [by_round[r]]),
            overhead_s=overhead,
            total_s=5.0,
        )
        for r in (1, 3)
    ]
    assert plans[0].batch_sizes != plans[1].batch_sizes


def test_theorem2_shape_against_the_formula():
    shape = theorem2_shape(
        gap=2.0,
        step_size=0.1,
        smoothness=2.0,
        rounds=10,
        inner_steps=3,
        batch_sizes=[10, 20, 40],
        mini_batch_sizes=[2, 4, 5],
        beta=0.5,
    )
    weight = (0.5 * 0.1 * 2.0 + 1) * (3 - 1 - 0.5) / (3 * 0.5)
    assert shape.optimisation == pytest.approx(2 * 3 * 2.0 / (10 * 0.1 * 1.5))
    assert shape.mini_batch_per_zeta == pytest.approx(weight * (3 / 2 + 3 / 4 + 3 / 5))
    assert shape.snapshot_per_xi == pytest.approx(weight * (3 / 10 + 3 / 20 + 3 / 40))
    assert shape.step_size_ok
    with pytest.raises(ValueError, match="β"):
        theorem2_shape(
            gap=1,
            step_size=0.1,
            smoothness=1,
            rounds=1,
            inner_steps=1,
            batch_sizes=[2, 2],
            mini_batch_sizes=[2, 2],
            beta=1.0,
        )


def test_fedhpg_plan_prints_a_plan_that_fedhpg_run_accepts(capsys):
    status = main(["--max-return", "1", "--pilot-rounds", "3", *COUNTED, "rounds=20"])
    out = capsys.readouterr().out
    assert status == 0
    assert "planned: bound" in out and "configured: bound" in out
    line = out.strip().splitlines()[-1]
    assert line.startswith("fedhpg-run ")
    run = compose(line.split()[1:])
    assert len(run.agents.budget["batch_size"]) == 4


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--tau-max", "0"], "local_iters_max must be ≥ 1"),
        (["--bogus"], "--bogus: not an option"),
        (["--budget-s", "0"], "--budget-s: must be > 0"),
        (["--budget-s", "abc"], "invalid float value"),
        (["algo=fedhpgvr"], "algo.name: the planner needs Theorem 1"),
        (["rouds=3"], "rouds: not a fedhpg key"),
        (["--budget-s", "0.001", *COUNTED, "--pilot-rounds", "1"], "--budget-s: no round"),
    ],
)
def test_fedhpg_plan_user_mistakes_are_one_line(args, says, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    try:
        status = main(args)
    except SystemExit as stop:  # argparse's own errors
        status = stop.code
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert len(err) == 1 and err[0].startswith("error: ") and says in err[0]
    assert list(tmp_path.iterdir()) == []


def test_fedhpg_plan_help(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0 and "--budget-s" in capsys.readouterr().out


def test_a_mistake_through_the_console_script(tmp_path):
    script = os.path.join(os.path.dirname(sys.executable), "fedhpg-plan")
    wrong = subprocess.run(
        [script, "--pilot-rounds", "x"], capture_output=True, text=True, cwd=tmp_path, check=False
    )
    assert wrong.returncode == 2
    assert wrong.stderr.strip().count("\n") == 0 and "invalid int value" in wrong.stderr
    assert list(tmp_path.iterdir()) == []
