"""Human-readable summaries of a run: the per-environment evaluation table."""

from __future__ import annotations

from typing import Any

from fedhpg.common.types import EvaluationStats


def evaluation_table(
    evaluation: dict[str, EvaluationStats],
    variants_params: dict[str, dict],
    compute: dict[str, str] | None = None,
    *,
    has_goal: bool = True,
) -> str:
    """A fixed-width table: one row per agent environment, success rate and returns, with
    what makes that agent different (its environment variant and compute budget). Without a
    goal (``has_goal`` False: every family but GridWorld) the success column shows "—": a
    rate of 0.00 would read as a failed task."""
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
        lines.append(
            f"{agent:<12} {_success(stats, has_goal):>8} {stats.return_mean:>8.3f} "
            f"{stats.discounted_return_mean:>9.3f} {stats.length_mean:>7.1f}  "
            f"{compute.get(agent, ''):<{width}}  {params}"
        )
    return "\n".join(lines)


def _success(stats: EvaluationStats, has_goal: bool) -> str:
    return f"{stats.success_rate:.2f}" if has_goal else "—"


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, list | tuple) and len(value) > 4:
        return f"[{len(value)} items]"
    return str(value)
