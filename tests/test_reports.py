"""What a run tells its user at the end and in its files: the final table (a row per agent up
to 20, a summary of quantiles and the worst agents beyond), the discount each agent really
uses, attackers marked in the log, the table and metrics.jsonl, no success rate where an
environment has no goal, and how many agent processes ``agents.per_host=auto`` starts."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from fedhpg.common.configuration.placement import agents_per_host
from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.runtime.cli import compose
from fedhpg.server.commands import api
from fedhpg.server.commands.launcher import agent_processes
from fedhpg.server.serving import final_report

TINY = ["rounds=2", "eval.every=2", "eval.episodes=2", "agents=homogeneous4"]


def _stats(value: float) -> EvaluationStats:
    return EvaluationStats(
        return_mean=value,
        return_std=0.0,
        discounted_return_mean=value / 2,
        success_rate=min(max(value, 0.0), 1.0),
        length_mean=10.0,
        episodes=2,
    )


def test_a_thousand_agents_end_on_a_summary_not_a_thousand_rows() -> None:
    run = compose(["agents=population", "agents.num_agents=1000"])
    ids = [f"agent-{k}" for k in range(1000)]
    evaluation = {agent: _stats(k / 1000) for k, agent in enumerate(ids)}
    evaluation["agent-617"] = _stats(-5.0)  # the worst
    text = final_report(run, evaluation, ids, has_goal=True)
    lines = text.splitlines()
    assert len(lines) < 20, text
    assert lines[0].split()[:2] == ["1000", "environments"]
    assert "median" in lines[0] and "10%" in lines[0] and "90%" in lines[0]
    returns = next(line for line in lines if line.startswith("return"))
    assert returns.split()[1] == "-5.000" and returns.split()[-1] == "0.999"
    assert [round(float(v), 1) for v in returns.split()[2:5]] == [0.1, 0.5, 0.9]
    worst = [line.split()[0] for line in lines if line.startswith("agent-")]
    assert worst == ["agent-617", "agent-0", "agent-1", "agent-2", "agent-3"]
    small = final_report(run, dict(list(evaluation.items())[:4]), ids[:4], has_goal=True)
    assert [line.split()[0] for line in small.splitlines()[2:]] == ids[:4], "a row each"


def test_the_table_shows_the_discount_the_agents_use() -> None:
    run = compose(["env=lunarlander", "agents=homogeneous4"])
    assert run.env.gamma == 1.0
    ids = [f"agent-{k}" for k in range(4)]
    text = final_report(run, {a: _stats(1.0) for a in ids}, ids, has_goal=False)
    rows = [line for line in text.splitlines() if line.startswith("agent-")]
    assert len(rows) == 4 and all("gamma=1," in row for row in rows), text


def test_attackers_are_marked_in_the_log_the_table_and_the_metrics(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        result = api.run(
            overrides=[*TINY, "attack=sign_flip", "attack.agents=[1,3]"],
            out_dir=tmp_path / "run",
        )
    said = [r.getMessage() for r in caplog.records if "attack" in r.getMessage()]
    assert any("sign_flip" in line and "agents 1, 3 attack" in line for line in said), said
    assert all(r["attack"] == {"kind": "sign_flip", "agents": [1, 3]} for r in result.records)
    lines = (tmp_path / "run/metrics.jsonl").read_text().splitlines()
    assert json.loads(lines[-1])["attack"]["agents"] == [1, 3]
    ids = [f"agent-{k}" for k in range(4)]
    assert result.last_evaluation is not None
    table = final_report(result.config, result.last_evaluation, ids, has_goal=True)
    marked = [line.split()[0] for line in table.splitlines() if " ! " in line]
    assert marked == ["agent-1", "agent-3"], table
    assert "! attacks (sign_flip): agent-1, agent-3" in table
    honest = api.run(overrides=TINY)
    assert all("attack" not in r for r in honest.records), "nothing marked without attackers"


def test_no_success_rate_where_the_environment_has_no_goal(tmp_path: Path) -> None:
    api.run(
        overrides=["env=cartpole", *TINY, "agents.budget.batch_size=[2]"],
        out_dir=tmp_path / "cartpole",
    )
    summary = json.loads((tmp_path / "cartpole/summary.json").read_text())
    assert {e["success_rate"] for e in summary["eval"].values()} == {None}
    assert (
        summary["variants"]["agent-0"]["gamma"] == compose(["env=cartpole"]).env.options["gamma"]
        or 0.98 < summary["variants"]["agent-0"]["gamma"] <= 0.999
    )
    api.run(overrides=TINY, out_dir=tmp_path / "grid")
    summary = json.loads((tmp_path / "grid/summary.json").read_text())
    assert all(isinstance(e["success_rate"], float) for e in summary["eval"].values())


@pytest.mark.parametrize(
    ("overrides", "cores", "processes"),
    [
        ([], 2, 4),  # the demo: a sleeping process per agent
        (["agents=population", "agents.num_agents=1000"], 2, 2),
        (["agents=population", "agents.num_agents=1000"], 16, 16),
        (["agents=population", "agents.num_agents=32"], 2, 32),
        (["agents=population", "agents.num_agents=48"], 64, 48),
        (["agents=population", "agents.num_agents=1000", "server.round_policy=buffered"], 2, 1000),
        (["agents=population", "agents.num_agents=1000", "agents.per_host=100"], 2, 10),
    ],
)
def test_per_host_auto_picks_processes_from_k_and_the_cores(
    overrides: list[str], cores: int, processes: int
) -> None:
    run = compose(overrides)
    per_host = agents_per_host(run, cores=cores)
    assert -(-run.agents.num_agents // per_host) == processes
    assert compose([]).agents.per_host == "auto", "the default"


def test_the_launcher_starts_hosts_that_cover_every_agent_once() -> None:
    run = compose(["agents=population", "agents.num_agents=1001"])
    covered: list[int] = []
    for _, agent_run in agent_processes(run):
        first = (
            agent_run.agent.first if agent_run.agent.first is not None else agent_run.agent.index
        )
        covered += range(
            first, first + (agent_run.agent.count if agent_run.agent.first is not None else 1)
        )
    assert covered == list(range(1001))
