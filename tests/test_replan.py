"""``agents.plan=theorem1``: the server re-plans B_k, τ_k every P rounds during a run.

- A device that slows down (agents.schedule) gets a smaller B_k·τ_k at the next plan, and the
  agents train with the plan in force (their trajectories are its B_k·τ_k): a real in-process
  run on the counted clock (deterministic).
- The same plan gives the same θ̃ in process and over the wire: one process per agent
  (``Train.budget``) and hosts of 3 + 1 agents (``TrainBatch.budgets``), the batched engine
  beside the loop training an attacker.
- A resumed run re-plans exactly as the uninterrupted one (the plan's window is checkpointed).
"""

from __future__ import annotations

from pathlib import Path

import torch

from fedhpg.server import api
from fedhpg.server.plan import configured_budgets, observed_seconds_per_trajectory

COUNTED = ["agents.clock=counted", "agents.virtual_clock=true"]
PLAN = ["agents.plan=theorem1", "algo.bound_estimates=true"]


def _plans(records: list[dict]) -> dict[int, dict]:
    return {r["round"]: r["plan"] for r in records if "plan" in r}


def _work(plan: dict) -> list[int]:
    return [b * t for b, t in zip(plan["batch_size"], plan["local_iters"], strict=True)]


def test_a_device_slowing_down_gets_a_smaller_budget_at_the_next_plan() -> None:
    """Periodic speeds of period 8, P = 2: the window of rounds 3-4 runs at 1.5× and 1.35×
    the base speed, that of rounds 5-6 at 1× and 0.65×. The plan made after round 6 prices
    each agent's trajectories dearer than the plan after round 4 did (by the speeds' ratio)
    and gives it less work per round (the slowest agent stays at the smallest budget, 2)."""
    overrides = [
        *COUNTED,
        *PLAN,
        "agents.plan_every=2",
        "agents.schedule=periodic",
        "agents.schedule_period_rounds=8",
        "agents.step_delays_s=[0.0]",
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


# CartPole population (B_k, τ_k, speeds per agent): the batched engine trains the honest
# agents, agent 2 attacks and is trained by the loop beside it (common/group.py's SplitGroup).
WIRE_RUN = [
    "env=cartpole", "agents=population", "rounds=3", "seed=5", "agents.num_agents=4",
    "agents.clock=counted", "eval.every=3", "eval.episodes=2", "attack.kind=sign_flip",
    "attack.agents=[2]", *PLAN, "agents.plan_every=1",
]  # fmt: skip


def test_a_plan_gives_the_same_theta_in_process_and_over_the_wire() -> None:
    here = api.run(overrides=WIRE_RUN)
    plans = _plans(here.records)
    assert sorted(plans) == [1, 2]
    # the plans change the budgets, so the comparison tests their delivery
    ran = {r["round"]: [a["trajectories"] for a in r["agents"]] for r in here.records}
    assert ran[2] == _work(plans[1]) and ran[3] == _work(plans[2]) and ran[1] != ran[2]
    # one process per agent (Train.budget); hosts of 3 + 1 agents (TrainBatch.budgets)
    for per_host in (1, 3):
        wire = api.run(overrides=[*WIRE_RUN, f"agents.per_host={per_host}"], distributed=True)
        assert torch.equal(here.theta, wire.theta), per_host
        assert _plans(wire.records) == plans, per_host


def test_a_resumed_run_re_plans_as_the_uninterrupted_one(tmp_path: Path) -> None:
    """Stopped after round 5, in the middle of a plan's window (P = 2): the window's first
    round comes back from the checkpoint, so the plan after round 6 and θ̃ are the same."""
    keys = [*COUNTED, *PLAN, "agents.plan_every=2", "seed=3", "eval.every=100", "eval.episodes=1"]
    # an explicit budget: the default (rounds × the first window's slowest round) follows
    # ``rounds``, which this resume raises
    keys += [
        "agents.schedule=periodic",
        "agents.schedule_period_rounds=6",
        "agents.plan_budget_s=2.0",
    ]
    out_dir = tmp_path / "run"
    api.run(overrides=[*keys, "rounds=5"], out_dir=out_dir)
    resumed = api.run(overrides=[*keys, "rounds=8", "resume=true"], out_dir=out_dir)
    whole = api.run(overrides=[*keys, "rounds=8"])
    assert [r["round"] for r in resumed.records] == list(range(1, 9))
    assert sorted(_plans(whole.records)) == [2, 4, 6]
    assert _plans(resumed.records) == _plans(whole.records)
    assert torch.equal(resumed.theta, whole.theta)
