"""Human-readable summaries of a run: the unified policy's evaluation per environment.

Up to :data:`TABLE_ROWS` agents the final table has a row per agent's environment; beyond, a
summary (quantiles over the agents' environments, then the worst few agents' rows), so that a
run of 1,000 agents ends on a screenful rather than 1,000 rows.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any

import numpy as np

from fedhpg.common.records.types import EvaluationStats

TABLE_ROWS = 20
"""Agents up to which the final table shows every one; beyond, :func:`evaluation_summary`."""
WORST_ROWS = 5
"""Agents the summary lists by name: those of the lowest returns."""
QUANTILES = (0.0, 0.1, 0.5, 0.9, 1.0)
ATTACKER_MARK = "!"

Describe = Callable[[str], tuple[str, dict[str, Any]]]
"""Agent id → (its compute budget, its environment variant's parameters), for a table row."""


def evaluation_of(records: dict[str, dict[str, Any]]) -> dict[str, EvaluationStats]:
    """An evaluation as metrics.jsonl and summary.json hold it (agent id → its statistics;
    ``success_rate`` null where the environment has no goal), as the server had it."""
    return {
        agent: EvaluationStats(**{**stats, "success_rate": stats["success_rate"] or 0.0})
        for agent, stats in records.items()
    }


def evaluation_table(
    evaluation: dict[str, EvaluationStats],
    variants_params: dict[str, dict[str, Any]],
    compute: dict[str, str] | None = None,
    *,
    has_goal: bool = True,
    attackers: Collection[str] = (),
) -> str:
    """A fixed-width table: one row per agent environment, success rate and returns, with
    what makes that agent different (its environment variant and compute budget). Without a
    goal (``has_goal`` False: every family but GridWorld) the success column shows "—": a
    rate of 0.00 would read as a failed task. ``attackers`` (agent ids) are marked "!"."""
    compute = compute or {}
    width = max([len(c) for c in compute.values()] + [7])
    header = (
        f"{'environment':<12} {'success':>8} {'return':>8} {'disc.ret':>9} {'length':>7}  "
        f"{'compute':<{width}}  environment variant"
    )
    lines = [header, "-" * len(header)]
    for agent, stats in evaluation.items():
        params = ", ".join(
            f"{key}={_short(value)}" for key, value in variants_params.get(agent, {}).items()
        )
        name = f"{agent} {ATTACKER_MARK}" if agent in attackers else agent
        lines.append(
            f"{name:<12} {_success(stats, has_goal):>8} {stats.return_mean:>8.3f} "
            f"{stats.discounted_return_mean:>9.3f} {stats.length_mean:>7.1f}  "
            f"{compute.get(agent, ''):<{width}}  {params}"
        )
    return "\n".join(lines)


def evaluation_summary(
    evaluation: dict[str, EvaluationStats],
    describe: Describe,
    *,
    has_goal: bool = True,
    attackers: Collection[str] = (),
    worst: int = WORST_ROWS,
) -> str:
    """Quantiles over the agents' environments of the return (and success rate, with a goal),
    then the table rows of the ``worst`` agents by return."""
    names = ["min", "10%", "median", "90%", "max"]
    header = f"{len(evaluation)} environments " + "".join(f"{n:>10}" for n in names)
    lines = [header, "-" * len(header)]
    columns = {"return": [s.return_mean for s in evaluation.values()]}
    columns["disc. return"] = [s.discounted_return_mean for s in evaluation.values()]
    if has_goal:
        columns["success"] = [s.success_rate for s in evaluation.values()]
    columns["length"] = [s.length_mean for s in evaluation.values()]
    for label, values in columns.items():
        points = np.quantile(np.asarray(values, dtype=np.float64), QUANTILES)
        lines.append(
            f"{label:<{len(header) - 10 * len(names)}}" + "".join(f"{p:>10.3f}" for p in points)
        )
    lowest = sorted(evaluation, key=lambda agent: (evaluation[agent].return_mean, agent))[:worst]
    described = {agent: describe(agent) for agent in lowest}
    lines += ["", f"the {len(lowest)} environments of the lowest return:"]
    lines.append(
        evaluation_table(
            {agent: evaluation[agent] for agent in lowest},
            {agent: params for agent, (_, params) in described.items()},
            {agent: compute for agent, (compute, _) in described.items()},
            has_goal=has_goal,
            attackers=attackers,
        )
    )
    return "\n".join(lines)


def evaluation_report(
    evaluation: dict[str, EvaluationStats],
    describe: Describe,
    *,
    has_goal: bool = True,
    attackers: Collection[str] = (),
    attack: str = "",
) -> str:
    """The final table (every agent up to :data:`TABLE_ROWS`, else the summary), with a line
    saying which agents attack (``attack``: the attack's name) when some do."""
    if len(evaluation) <= TABLE_ROWS:
        described = {agent: describe(agent) for agent in evaluation}
        text = evaluation_table(
            evaluation,
            {agent: params for agent, (_, params) in described.items()},
            {agent: compute for agent, (compute, _) in described.items()},
            has_goal=has_goal,
            attackers=attackers,
        )
    else:
        text = evaluation_summary(evaluation, describe, has_goal=has_goal, attackers=attackers)
    if attackers:
        text += (
            f"\n{ATTACKER_MARK} attacks ({attack}): {', '.join(_ids(list(attackers)))} "
            "(attack.agents; their environments are evaluated as every agent's)"
        )
    return text


def _ids(agents: list[str]) -> list[str]:
    return agents if len(agents) <= 10 else [*agents[:10], f"… {len(agents)} in all"]


def _success(stats: EvaluationStats, has_goal: bool) -> str:
    return f"{stats.success_rate:.2f}" if has_goal else "—"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, list | tuple) and len(value) > 4:
        return f"[{len(value)} items]"
    return str(value)
