"""Buffered asynchronous rounds (server/buffered.py) on the in-process pool, counted clock.

Real agents (GridWorld, the demo's four devices at speeds 1/1/0.5/0.25), real run
directories and checkpoints; nothing is mocked.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.learning.group import TIMING_STATS
from fedhpg.common.records.types import UpdateStats
from fedhpg.server.buffered import BufferedSchedule, InFlight, buffer_rows
from fedhpg.server.commands import api
from fedhpg.server.commands.plot import Run, series
from fedhpg.server.coordinator import RoundRecord

COUNTED = ["agents.clock=counted", "agents.virtual_clock=true", "server.tensorboard=false"]
BASE = [*COUNTED, "seed=3", "rounds=8", "eval.every=8", "eval.episodes=2"]
BUFFERED = ["server.round_policy=buffered"]
WALL_FIELDS = ("wall_time_s", "round_time_s")


def _agents(agents: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each agent's entry without its CPU times (``compute_s`` and the engine's split of it)."""
    return [{k: v for k, v in a.items() if k not in ("compute_s", *TIMING_STATS)} for a in agents]


def _figures(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records without what is measured on this machine's clock (wall times and each
    agent's ``compute_s``): everything else is determined by the run."""
    return [
        {k: _agents(v) if k == "agents" else v for k, v in r.items() if k not in WALL_FIELDS}
        for r in records
    ]


def _item(
    agent: int,
    version: int,
    arrival_s: float,
    theta: torch.Tensor,
    base: torch.Tensor | None = None,
) -> InFlight:
    """An in-flight update θ_k = ``theta`` started from θ̃_version = ``base`` (default 0)."""
    stats = UpdateStats(trajectories=1, env_steps=1, compute_s=0.0, train_return=0.0)
    return InFlight(
        agent=agent,
        version=version,
        dispatch=1,
        arrival_s=arrival_s,
        agent_id=f"agent-{agent}",
        theta=theta,
        stats=stats,
        delta=theta - (torch.zeros_like(theta) if base is None else base),
    )


def test_buffered_run_is_bit_identical_twice() -> None:
    """Two runs under the counted virtual clock: the same θ̃ and every record's figures
    (staleness, emulated clock, agents' stats, evaluations) bit for bit; and asynchrony
    happened: some aggregated updates were stale, and the clock is the M-th arrival's."""
    overrides = [*BASE, *BUFFERED, "server.buffer_size=2"]
    first, second = api.run(overrides=overrides), api.run(overrides=overrides)
    assert torch.equal(first.theta, second.theta)
    assert _figures(first.records) == _figures(second.records)
    clocks = [r["emulated_clock_s"] for r in first.records]
    assert clocks == sorted(clocks) and clocks[0] > 0
    assert all(len(r["agents"]) == 2 == len(r["staleness"]) for r in first.records)
    assert max(s for r in first.records for s in r["staleness"]) > 0
    # fedhpg-plot's emulated-time axis is that clock, not a sum of the buffers' slowest
    x, _ = series(Run(Path("run"), {}, first.records), "emulated", "eval_return")
    assert x.tolist() == [r["emulated_clock_s"] for r in first.records if "eval" in r]


def test_buffer_of_all_agents_is_a_synchronous_round() -> None:
    """M = K: each buffer holds the K fresh updates from one θ̃, each agent's n-th update is
    its round-n update, so θ̃ and the agents' stats equal wait_all's bit for bit."""
    buffered = api.run(overrides=[*BASE, *BUFFERED])
    synchronous = api.run(overrides=BASE)
    assert torch.equal(buffered.theta, synchronous.theta)
    for a, s in zip(buffered.records, synchronous.records, strict=True):
        assert _agents(a["agents"]) == _agents(s["agents"]) and a.get("eval") == s.get("eval")
        assert a["staleness"] == [0, 0, 0, 0]
    # the clock is the sum of the rounds' slowest arrivals, as a synchronous round waits
    slowest = sum(max(a["emulated_s"] for a in r["agents"]) for r in synchronous.records)
    assert math.isclose(buffered.records[-1]["emulated_clock_s"], slowest, rel_tol=1e-12)


def test_arrivals_at_the_same_time_go_in_agent_order() -> None:
    schedule = BufferedSchedule()
    theta = torch.zeros(3)
    for agent in (3, 1, 2, 0):
        schedule.push(_item(agent, 0, 0.5 if agent else 0.7, theta))
    assert [schedule.pop().agent for _ in range(4)] == [1, 2, 3, 0]
    assert schedule.clock_s == 0.7


def test_staleness_weights_make_fedbuffs_mean_change() -> None:
    """The rows the strategy averages: their mean is θ̃ + (1/M) Σ w(s_k) Δ_k, w = 1/√(1+s);
    a fresh update is θ_k itself."""
    theta = torch.tensor([1.0, -2.0, 0.5])
    fresh = _item(0, 5, 1.0, torch.tensor([1.0, 0.0, 0.0]), base=theta)
    old = _item(1, 2, 1.0, theta * 3)
    rows = buffer_rows(ServerConfig(), theta, [old, fresh], current=5)
    assert [k for k, _, _ in rows] == [0, 1]
    expected = theta + (fresh.delta + old.delta / math.sqrt(1.0 + 3)) / 2
    mean = torch.stack([row for _, row, _ in rows]).mean(dim=0)
    assert torch.allclose(mean, expected, rtol=1e-6, atol=1e-6)
    assert torch.equal(rows[0][1], fresh.theta)
    constant = buffer_rows(ServerConfig(staleness_weight="constant"), theta, [fresh, old], 5)
    assert torch.equal(constant[1][1], theta + old.delta)


def test_staleness_bound_drops_old_updates_and_restarts_their_agents() -> None:
    """max_staleness=0 with M=2 of 4 at speeds 1/1/0.5/0.25: the slow agents' updates from
    older θ̃s are dropped (recorded with their staleness) and never aggregated."""
    run = api.run(overrides=[*BASE, *BUFFERED, "server.buffer_size=2", "server.max_staleness=0"])
    assert all(r["staleness"] == [0, 0] for r in run.records)
    stale = {a: s for r in run.records for a, s in r.get("stale", {}).items()}
    assert "agent-3" in stale and min(stale.values()) >= 1
    # the dropped updates' trajectories were sampled: they count on the x-axis
    aggregated = sum(a["trajectories"] for r in run.records for a in r["agents"]) / 4
    assert run.records[-1]["trajectories_per_agent"] > aggregated


def test_crash_and_resume_continue_the_uninterrupted_run_exactly(tmp_path: Path) -> None:
    """A run that dies after round 4 (its checkpoint written) and is resumed ends with the θ̃
    and the records of the run never interrupted: the checkpoint holds the in-flight updates,
    their versions and arrival times and the emulated clock."""
    overrides = [*BASE, *BUFFERED, "server.buffer_size=3", "server.max_staleness=2"]

    class Crash(Exception):
        pass

    def crash_after_4(record: RoundRecord, _: torch.Tensor) -> None:
        if record.round == 4:
            raise Crash

    out_dir = tmp_path / "run"
    with pytest.raises(Crash):
        api.run(overrides=overrides, out_dir=out_dir, callbacks=[crash_after_4])
    resumed = api.run(overrides=[*overrides, "resume=true"], out_dir=out_dir)
    uninterrupted = api.run(overrides=overrides)
    assert torch.equal(resumed.theta, uninterrupted.theta)
    assert _figures(resumed.records) == _figures(uninterrupted.records)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["server.buffer_size=5"], "server.buffer_size: got 5, must be <= agents.num_agents=4"),
        (["server.buffer_size=0"], "server.buffer_size: got 0, must be an integer >= 1"),
        (["server.max_staleness=-1"], "server.max_staleness: got -1, must be an integer >= 0"),
        (["server.staleness_weight=linear"], "server.staleness_weight: got 'linear', allowed"),
        (
            ["strategy.participation.mode=uniform", "strategy.participation.per_round=2"],
            "strategy.participation.mode: got 'uniform'; server.round_policy=buffered",
        ),
    ],
)
def test_bad_buffered_options_are_named(overrides: list[str], message: str) -> None:
    with pytest.raises(ConfigError) as error:
        api.run(overrides=[*BASE, *BUFFERED, *overrides])
    assert str(error.value).startswith(message)


def test_distributed_buffered_with_agent_hosts_is_refused_before_anything_starts(
    tmp_path: Path,
) -> None:
    refusal = r"agents\.per_host: got 2; server\.round_policy=buffered takes one agent"
    with pytest.raises(ConfigError, match=refusal):
        api.run(
            overrides=[*BASE, *BUFFERED, "agents.per_host=2"],
            distributed=True,
            out_dir=tmp_path / "run",
        )
    assert not (tmp_path / "run").exists()


def test_deadline_in_process_is_on_the_emulated_clock() -> None:
    """In process nothing waits on the wall clock: the deadline cuts the updates whose
    emulated time exceeds it (the 0.25-speed agent here), and they are stragglers."""
    run = api.run(overrides=[*BASE, "server.round_policy=deadline", "server.round_deadline_s=0.7"])
    for record in run.records:
        assert all(a["emulated_s"] <= 0.7 for a in record["agents"])
        assert record["stragglers"] == ["agent-3"]


def test_buffered_resume_of_a_synchronous_checkpoint_is_refused(tmp_path: Path) -> None:
    """A checkpoint of wait_all rounds holds no in-flight updates: resuming it as buffered
    rounds could not continue any run exactly, so it is refused, naming the key."""
    out_dir = tmp_path / "run"
    api.run(overrides=[*BASE, "rounds=1"], out_dir=out_dir)
    with pytest.raises(ConfigError, match=r"server\.round_policy: got 'buffered', but the"):
        api.run(overrides=[*BASE, *BUFFERED, "resume=true"], out_dir=out_dir)
