"""The distributed runtime with real processes over loopback TCP.

Equivalence: a federation of agent processes ends with exactly the in-process runner's θ.
Heterogeneity: emulated device time follows the speed factors; rounds wait for the slowest.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest
import torch
from procs import processes, start

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.coordinator import RoundRecord

ROUNDS = 4
TIMEOUT_S = 180


def _overrides(algo: str) -> list[str]:
    return [
        f"rounds={ROUNDS}",
        "seed=7",
        f"algo.name={algo}",
        "agents.num_agents=3",
        "agents.budget.batch_size=[6,8,10]",
        "agents.budget.local_iters=[1,2,3]",
        "++agents.budget.inner_steps=[2,3,2]",
        "++agents.budget.mini_batch_size=[3]",
        "agents.speeds=[1.0,1.0,0.25]",
        "agents.step_delays_s=[0]",
        "eval.every=2",
        "eval.episodes=10",
    ]


def _run_federation(tmp_path: Path, overrides: list[str]) -> Path:
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*overrides, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        stdout, stderr = launcher.communicate(timeout=TIMEOUT_S)
    assert launcher.returncode == 0, stderr[-3000:]
    assert "run directory:" in stdout and "agent-1" in stdout
    return out_dir


@pytest.mark.parametrize(
    ("algo", "transport", "extra"),
    [
        ("fedhpg", "tcp", ["strategy=mean"]),
        ("fedhpgvr", "tcp", ["strategy=weighted"]),
        ("fedhpg", "ipc", ["strategy=median"]),
        pytest.param(  # make test-long; fast cover: tests/test_federation.py::
            # test_distributed_theta_equals_in_process_bit_for_bit[median-ipc] (a robust rule
            # over the wire) and tests/test_strategies.py::test_trimmed_mean_drops_the_extremes
            "fedhpg",
            "tcp",
            ["strategy=trimmed_mean", "strategy.params.trim_fraction=0.34"],
            marks=pytest.mark.slow,
        ),
        ("fedhpgvr", "tcp", ["strategy=fedadam", "strategy.params.step_size=0.05"]),
        ("fedhpg", "tcp", ["strategy=mean", "server.max_update_norm=0.3"]),
    ],
    ids=["mean", "weighted-vr", "median-ipc", "trimmed_mean", "fedadam-vr", "update-norm-bound"],
)
def test_distributed_theta_equals_in_process_bit_for_bit(
    tmp_path: Path, algo: str, transport: str, extra: list[str]
) -> None:
    endpoint = [f"server.transport={transport}", f"server.ipc_path={tmp_path / 'fed.sock'}"]
    out_dir = _run_federation(tmp_path, _overrides(algo) + extra + endpoint)
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == ROUNDS
    in_process: list[RoundRecord] = []
    expected = run_in_process(
        compose(_overrides(algo) + extra), on_round=[lambda record, _: in_process.append(record)]
    )
    assert torch.equal(checkpoint.theta, expected)

    records = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["round"] for r in records] == list(range(1, ROUNDS + 1))
    assert [sorted(r["eval"]) for r in records if "eval" in r] == [
        ["agent-0", "agent-1", "agent-2"]
    ] * 2
    assert [sorted(r.get("failures", {})) for r in records] == [
        sorted(r.failures) for r in in_process
    ], "both pools reject the same updates"
    if "server.max_update_norm=0.3" in extra:
        assert all(r["failures"] for r in records), "the bound is exercised every round"
    for record in records:
        ids = [f"agent-{k}" for k in range(3) if f"agent-{k}" not in record.get("failures", {})]
        assert [a["id"] for a in record["agents"]] == ids
        slowest = max(a["local_wall_s"] for a in record["agents"])
        assert record["round_time_s"] >= slowest, "a round waits for every agent (Algorithm 1)"


def test_emulated_time_follows_the_speed_factor(tmp_path: Path) -> None:
    """Equal work (same B and τ, one-step episodes of an identical environment, so both agents
    do the same arithmetic), speeds 1 and 0.25: each agent's emulated time is its measured
    compute over its speed, exactly; the slow agent's is about 4× the fast one's (median over
    rounds 2-10; round 1 pays one-off warm-up costs); and it really took that long."""
    overrides = [
        "rounds=10",
        "seed=1",
        "env.family=cartpole",
        "env.level=0",
        "env.horizon=1",
        "agents.num_agents=2",
        "agents.budget.batch_size=[256]",
        "agents.budget.local_iters=[3]",
        "agents.speeds=[1.0,0.25]",
        "agents.step_delays_s=[0]",
        "algo.step_size=0.01",
        "policy.hidden=[512,512]",
        "eval.every=10",
        "eval.episodes=2",
    ]
    out_dir = _run_federation(tmp_path, overrides)
    records = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]

    assert all(a["env_steps"] == 256 * 3 for r in records for a in r["agents"]), "equal work"
    for record in records:
        for agent, speed in zip(record["agents"], (1.0, 0.25), strict=True):
            assert agent["emulated_s"] == pytest.approx(agent["compute_s"] / speed, rel=1e-9)
    # Median of the per-round ratios: one round disturbed by the machine cannot decide it. The
    # bounds are the measured clock's, not the code's: equal work measured 0.91-1.05x as much
    # CPU time in the slow agent here (medians 3.65-4.19 over 20 runs, idle and under CPU
    # hogs), and 1.23-1.30x on two CI runs with the other xdist worker busy (medians 4.92,
    # 5.20). 4 ÷/× 1.6 holds those and still fails a speed ignored (1), inverted (1/4) or
    # applied twice (16), or a slept slowdown counted as compute (16).
    ratios = [r["agents"][1]["emulated_s"] / r["agents"][0]["emulated_s"] for r in records[1:]]
    assert 4 / 1.6 <= statistics.median(ratios) <= 4 * 1.6, ratios
    for agent in (r["agents"][1] for r in records):
        assert agent["local_wall_s"] >= 0.9 * agent["emulated_s"], "the slowdown was slept"
