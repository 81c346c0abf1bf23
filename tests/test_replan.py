"""``agents.plan=theorem1``: the server re-plans B_k, τ_k every P rounds during a run.

- A device that slows down (agents.schedule) gets a smaller B_k·τ_k at the next plan, and the
  agents train with the plan in force (their trajectories are its B_k·τ_k): a real in-process
  run on the counted clock (deterministic).
- The same plan gives the same θ̃ in process and over the wire: one process per agent
  (``Train.budgets``, one entry) and hosts of 3 + 3 + 2 agents (one entry per agent), the
  compiled backend beside the engine training an attacker.
- A resumed run re-plans exactly as the uninterrupted one (the plan's window is checkpointed).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
import torch

from fedhpg.common.learning.bounds import theorem1_terms
from fedhpg.common.learning.planning import Constants, Limits, plan_for_rounds
from fedhpg.server.commands import api
from fedhpg.server.commands.plan import configured_budgets, observed_seconds_per_trajectory

COUNTED = ["agents.clock=counted", "agents.virtual_clock=true"]
PLAN = ["agents.plan=theorem1", "algo.bound_estimates=true"]


def _plans(records: list[dict]) -> dict[int, dict]:
    return {r["round"]: r["plan"] for r in records if "plan" in r}


def _work(plan: dict) -> list[int]:
    return [b * t for b, t in zip(plan["batch_size"], plan["local_iters"], strict=True)]


def test_a_device_slowing_down_gets_a_smaller_budget_at_the_next_plan() -> None:
    """Periodic speeds of period 8, P = 2: the window of rounds 3-4 runs at 1.5× and 1.35×
    the base speed, that of rounds 5-6 at 1× and 0.65×. The round time held is the first two
    rounds' (the default), so the plan made after round 6 gives every agent less work per
    round than the plan after round 4 (unless already at the smallest budget, 2·1)."""
    overrides = [
        *COUNTED,
        *PLAN,
        "agents.plan_every=2",
        "agents.schedule=periodic",
        "agents.schedule_period_rounds=8",
        "agents.step_delays_s=[0.0]",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[2]",
        "eval.every=100",
        "eval.episodes=1",
        "rounds=7",
    ]
    result = api.run(overrides=overrides)
    run, records = result.config, result.records
    plans = _plans(records)
    assert sorted(plans) == [2, 4, 6]
    fast, slow = plans[4], plans[6]
    by_round = {r["round"]: r for r in records}
    # per env step the counted clock's price is 1/speed alone (per trajectory it also follows
    # the episodes' lengths, which learning changes): the devices did slow down
    step_fast = observed_seconds_per_trajectory(run, [by_round[3], by_round[4]], per="env_steps")
    step_slow = observed_seconds_per_trajectory(run, [by_round[5], by_round[6]], per="env_steps")
    batches, iters = configured_budgets(run)
    for k in range(run.agents.num_agents):
        assert step_slow[k] > 1.4 * step_fast[k], k
        smallest = 2 * 1
        assert _work(slow)[k] < _work(fast)[k] or _work(fast)[k] == smallest, k
        ran = {r["round"]: next(a for a in r["agents"] if a["index"] == k) for r in records}
        # the first P rounds run the configured budgets, then the plan in force
        for round_number, work in ((2, batches[k] * iters[k]), (5, _work(fast)[k])):
            assert ran[round_number]["trajectories"] == work
        assert ran[6]["trajectories"] == _work(fast)[k] and ran[7]["trajectories"] == _work(slow)[k]
    assert sum(_work(slow)) < sum(_work(fast))


# CartPole population (B_k, τ_k, speeds per agent): the compiled backend trains the honest
# agents, agent 2 attacks and is trained by the engine beside it (common/learning/group.py's
# SplitGroup). A plan needs one agent's L̂ > 0, and each agent's secant estimate is positive
# about half the time early on: with 8 agents a round without a plan is a 1-in-200 event.
WIRE_RUN = [
    "env=cartpole", "agents=population", "rounds=3", "seed=5", "agents.num_agents=8",
    "agents.clock=counted", "eval.every=3", "eval.episodes=2", "attack.kind=sign_flip",
    "attack.agents=[2]", *PLAN, "agents.plan_every=1",
]  # fmt: skip


def test_a_plan_gives_the_same_theta_in_process_and_over_the_wire(tmp_path: Path) -> None:
    here = api.run(overrides=WIRE_RUN)
    plans = _plans(here.records)
    assert sorted(plans) == [1, 2]
    # the plans change the budgets, so the comparison tests their delivery
    ran = {r["round"]: [a["trajectories"] for a in r["agents"]] for r in here.records}
    assert ran[2] == _work(plans[1]) and ran[3] == _work(plans[2]) and ran[1] != ran[2]
    # one process per agent (one Train.budgets entry); hosts of 3 + 3 + 2 (one per agent)
    for per_host in (1, 3):
        wire = api.run(
            overrides=[*WIRE_RUN, f"agents.per_host={per_host}"],
            distributed=True,
            out_dir=tmp_path / f"per-host-{per_host}",
        )
        assert torch.equal(here.theta, wire.theta), per_host
        assert _plans(wire.records) == plans, per_host


class _Crash(RuntimeError):
    pass


def _crash_after(round_number: int):
    def callback(record, _theta) -> None:
        if record.round == round_number:
            raise _Crash  # after the round's checkpoint: the callbacks given come last

    return callback


def test_a_resumed_run_re_plans_as_the_uninterrupted_one(tmp_path: Path) -> None:
    """Stopped after round 5, in the middle of a plan's window (P = 2): the window's first
    round comes back from the checkpoint, so the plan after round 6 and θ̃ are the same."""
    keys = [*COUNTED, *PLAN, "agents.plan_every=2", "seed=3", "eval.every=100", "eval.episodes=1"]
    keys += ["agents.schedule=periodic", "agents.schedule_period_rounds=6", "rounds=8"]
    out_dir = tmp_path / "run"
    with pytest.raises(_Crash):
        api.run(overrides=keys, out_dir=out_dir, callbacks=[_crash_after(5)])
    resumed = api.run(overrides=[*keys, "resume=true"], out_dir=out_dir)
    whole = api.run(overrides=keys)
    assert [r["round"] for r in resumed.records] == list(range(1, 9))
    assert sorted(_plans(whole.records)) == [2, 4, 6]
    assert _plans(resumed.records) == _plans(whole.records)
    assert torch.equal(resumed.theta, whole.theta)


@pytest.mark.parametrize(
    ("gap", "smoothness", "second_moment", "rounds"),
    [
        (1.0, 0.5, 2.0, 30),  # τ > 1 costs heterogeneity: τ = 1 wins
        (50.0, 0.05, 0.01, 10),  # a large gap, little drift: more local steps pay
        (5.0, 0.2, 0.1, 3),
    ],
)
def test_a_plan_for_fixed_rounds_is_the_brute_force_minimum(gap, smoothness, second_moment, rounds):
    """What the re-planner solves: T fixed (the rounds left), every agent's round within the
    round time; eq. 7 over every budget in the box (K = 3) agrees with the search."""
    constants = Constants(
        gap=gap, step_size=0.5, smoothness=smoothness, second_moment=second_moment,
        variances=(1.0, 3.0, 0.5),
    )  # fmt: skip
    seconds, overhead = [0.01, 0.02, 0.04], [0.002, 0.002, 0.005]
    limits = Limits(batch_min=2, batch_max=7, local_iters_max=3)
    round_s = 0.3
    plan = plan_for_rounds(
        constants=constants,
        seconds_per_trajectory=seconds,
        overhead_s=overhead,
        total_s=round_s * rounds,
        rounds=rounds,
        limits=limits,
    )
    best = math.inf
    box = list(itertools.product(range(2, 8), range(1, 4)))
    for choice in itertools.product(box, repeat=3):
        times = [t * b * c + o for (b, t), c, o in zip(choice, seconds, overhead, strict=True)]
        if max(times) > round_s:
            continue
        terms = theorem1_terms(
            gap=gap,
            step_size=0.5,
            smoothness=smoothness,
            second_moment=second_moment,
            variances=constants.variances,
            local_iters=[t for _, t in choice],
            batch_sizes=[b for b, _ in choice],
            rounds=rounds,
        )
        if terms.step_size_ok:
            best = min(best, terms.total)
    assert plan.rounds == rounds and plan.round_s <= round_s
    assert plan.step_size_ok and plan.bound == pytest.approx(best, rel=1e-12)
