"""Populations (``agents.population``): per-agent budgets and devices drawn from seeded
distributions or read from a trace, lazily per index."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from procs import processes, start

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.heterogeneity.device import device_for
from fedhpg.common.heterogeneity.population import population_value
from fedhpg.common.learning.components import agent_profile, validate_run
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

ROOT = Path(__file__).resolve().parents[1]
TRACE = ROOT / "docs" / "device-trace.csv"


def _drawn(*extra: str) -> RunConfig:
    return compose(["agents=population", *extra])


def _profile(run: RunConfig, k: int) -> tuple[object, ...]:
    device = device_for(run, k)
    return (agent_profile(run, k), device.speed, device.step_delay_s, device.latency_s)


def test_same_seed_same_agents_and_lazy() -> None:
    big = _drawn("agents.num_agents=10000", "seed=3")
    again = _drawn("agents.num_agents=10000", "seed=3")
    assert [_profile(big, k) for k in (0, 17, 9999)] == [_profile(again, k) for k in (0, 17, 9999)]
    # agent k's draw depends on (seed, k, field) only: K does not move it, the seed does
    small = _drawn("agents.num_agents=20", "seed=3")
    assert _profile(small, 17) == _profile(big, 17)
    other = _drawn("agents.num_agents=10000", "seed=4")
    assert [device_for(other, k).speed for k in range(20)] != [
        device_for(big, k).speed for k in range(20)
    ]
    start_s = time.perf_counter()
    profile = agent_profile(big, 9999)
    device = device_for(big, 9999)
    elapsed = time.perf_counter() - start_s
    assert profile.budget.batch_size in (4, 8, 16) and 0.25 <= device.speed <= 4.0
    # one agent costs well under a millisecond here; 10 000 of them would take far longer
    assert elapsed < 0.05, f"agent 9999 took {elapsed:.4f} s"


def test_drawn_frequencies_and_median_match_the_distribution() -> None:
    """n = 4000 agents. A choice frequency p̂ has sd sqrt(p(1-p)/n) ≤ 0.008: 4.5 sd = 0.036.
    The sample median of a lognormal(median m, σ) has sd ≈ m σ sqrt(π/2) / sqrt(n) ≈ 0.0099
    for σ = 0.5 (the density at the median is 1/(m σ sqrt(2π))): 4.5 sd ≈ 0.045."""
    n = 4000
    run = _drawn(
        f"agents.num_agents={n}",
        "seed=11",
        "agents.population.draw.speed.min=0.01",
        "agents.population.draw.speed.max=100",
    )
    batches = np.array([population_value(run, k, "batch_size") for k in range(n)])
    for value, p in zip((4, 8, 16), (0.5, 0.3, 0.2), strict=True):
        tolerance = 4.5 * math.sqrt(p * (1 - p) / n)
        assert abs(float(np.mean(batches == value)) - p) < tolerance, value
    iters = np.array([population_value(run, k, "local_iters") for k in range(n)])
    for value in (1, 2, 3):
        assert abs(float(np.mean(iters == value)) - 1 / 3) < 4.5 * math.sqrt(2 / 9 / n)
    speeds = np.array([device_for(run, k).speed for k in range(n)])
    sd_median = 0.5 * math.sqrt(math.pi / 2) / math.sqrt(n)
    assert abs(float(np.median(speeds)) - 1.0) < 4.5 * sd_median
    # the preset's clip: every drawn speed within [min, max]
    clipped = _drawn("agents.num_agents=500")
    assert all(0.25 <= device_for(clipped, k).speed <= 4.0 for k in range(500))


def test_trace_rows_read_exactly_and_wrap_around() -> None:
    lines = [line for line in TRACE.read_text().splitlines() if not line.startswith("#")]
    header, *rows = [line.split(",") for line in lines]
    assert len(rows) == 20
    run = compose(
        [
            "agents=homogeneous4",
            "agents.num_agents=45",
            "agents.population.kind=trace",
            f"agents.population.trace={TRACE}",
        ]
    )
    validate_run(run)
    for k in (0, 7, 19, 20, 44):
        row = dict(zip(header, rows[k % 20], strict=True))
        profile, device = agent_profile(run, k), device_for(run, k)
        assert profile.budget.batch_size == int(row["batch_size"])
        assert profile.budget.local_iters == int(row["local_iters"])
        assert device.speed == float(row["speed"]) == profile.speed
        assert device.step_delay_s == float(row["step_delay_s"])
        assert device.latency_s == float(row["latency_s"])
        assert device.bandwidth_mbps == float(row["bandwidth_mbps"])
        # a field the trace leaves keeps its list
        assert device.step_cost_s == run.agents.step_costs_s[0]


def test_default_is_the_lists_unchanged() -> None:
    run = compose([])
    assert run.agents.population.kind == "none"
    budgets = [agent_profile(run, k).budget for k in range(4)]
    assert [b.batch_size for b in budgets] == run.agents.budget["batch_size"]
    assert [device_for(run, k).speed for k in range(4)] == run.agents.speeds
    # a population setting one field leaves the others to their lists
    partial = compose(
        ["agents.population.kind=drawn", "+agents.population.draw.speed={choice: [2.0]}"]
    )
    assert [device_for(partial, k).speed for k in range(4)] == [2.0] * 4
    assert [agent_profile(partial, k).budget for k in range(4)] == budgets
    assert [device_for(partial, k).step_delay_s for k in range(4)] == run.agents.step_delays_s


def _write(tmp_path: Path, text: str) -> str:
    path = tmp_path / "trace.csv"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["agents.population.kind=crowd"], r"agents\.population\.kind"),
        (["agents.population.draw.speed.lognormal.sigma=-1"], r"draw\.speed\.lognormal"),
        (["agents.population.draw.batch_size.weights=[1,2]"], r"draw\.batch_size\.weights"),
        (["agents.population.draw.speed={uniform: {low: 0, high: 1}}"], r"draw\.speed"),
        (["agents.population.draw.local_iters={lognormal: {median: 2, sigma: 1}}"], r"local_it"),
        (["agents.population.kind=trace"], r"agents\.population\.draw"),
    ],
)
def test_bad_distribution_is_one_named_key(overrides: list[str], key: str) -> None:
    with pytest.raises(ConfigError, match=key) as caught:
        validate_run(_drawn(*overrides))
    assert "\n" not in str(caught.value)


def test_bad_trace_is_one_line_naming_the_row(tmp_path: Path) -> None:
    def trace(path: str) -> RunConfig:
        return compose(["agents.population.kind=trace", f"agents.population.trace={path}"])

    with pytest.raises(ConfigError, match=r"agents\.population\.trace: .*missing\.csv"):
        validate_run(trace(str(tmp_path / "missing.csv")))
    bad_batch = _write(tmp_path, "agent,batch_size,speed\n0,8,1.0\n1,0,1.0\n")
    with pytest.raises(ConfigError, match=r"row 1\.batch_size: got 0") as caught:
        validate_run(trace(bad_batch))
    assert "\n" not in str(caught.value)
    with pytest.raises(ConfigError, match=r"row 0\.speed: got 0"):
        validate_run(trace(_write(tmp_path, "agent,speed\n0,0\n")))
    with pytest.raises(ConfigError, match=r"row 1\.agent"):
        validate_run(trace(_write(tmp_path, "agent,speed\n0,1\n2,1\n")))
    with pytest.raises(ConfigError, match=r"'speeed' is no budget or device field"):
        validate_run(trace(_write(tmp_path, "agent,speeed\n0,1\n")))


def test_fedhpg_run_bad_population_exits_2_in_one_line(tmp_path: Path) -> None:
    done = subprocess.run(
        [
            str(Path(sys.executable).parent / "fedhpg-run"),
            "agents.population.kind=trace",
            f"agents.population.trace={tmp_path / 'nope.csv'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"error: agents.population.trace: {tmp_path / 'nope.csv'}: No such file or directory"
    ]
    assert list(tmp_path.iterdir()) == []


RUN = ["agents=population", "agents.num_agents=6", "rounds=2", "seed=2", "eval.every=2"]
RUN += ["eval.episodes=2", "agents.clock=counted"]


def test_population_run_in_process_equals_fedhpg_run(tmp_path: Path) -> None:
    """Six drawn agents, two rounds: the in-process pool and agent processes reach the same
    θ̃ and the same counted emulated times, bit for bit."""
    records: list[list[float]] = []
    theta = run_in_process(
        compose(RUN),
        on_round=[lambda record, _: records.append(list(record.result.stats.emulated_s))],
    )
    assert len(records) == 2 and len(set(records[0])) > 1, "the drawn devices differ"
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*RUN, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        _, stderr = launcher.communicate(timeout=120)
    assert launcher.returncode == 0, stderr[-3000:]
    lines = (out_dir / "metrics.jsonl").read_text().splitlines()
    assert [[a["emulated_s"] for a in json.loads(line)["agents"]] for line in lines] == records
    final = latest_valid_checkpoint(out_dir / "checkpoints")
    assert final is not None and torch.equal(final.theta, theta)
