"""The round's Theorem 1 bound (eq. 7) in ``metrics.jsonl`` when ``algo.bound_estimates`` is on:
its four terms from the constants the round's agents estimated (``common/learning/bounds.py``).

Readings (the paper leaves these open; stated once here and in docs/metrics.md):
- the K of eq. 7 is the round's participants, their σ̂_k², B_k and τ_k;
- M is the largest M̂_k, L the largest L̂_k (agents with τ_k ≥ 2 estimate one; a round with
  none has no L, and the three terms that need it are left out);
- γ is ``algo.step_size`` and T is ``rounds``; the first term needs J(θ*) − J(θ_0), which no
  run knows, so it is reported per unit of that gap (``optimisation_per_unit_gap``);
- V = 1.
The theorem assumes plain local SGD; with ``algo.optimizer=adam`` the figures are reported
all the same, for what they say about the variance and drift.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.learning.bounds import theorem1_terms
from fedhpg.common.learning.components import agent_profile, planned_budget
from fedhpg.common.records.types import RoundResult


def round_bound(
    run: RunConfig,
    result: RoundResult,
    planned: Mapping[int, Mapping[str, int]] | None = None,
) -> dict[str, Any] | None:
    """The ``bound`` field of a round record, or None when the agents measured nothing;
    ``planned``: the round's planned budgets (``agents.plan``), else the configured ones."""
    algorithm = result.stats.algorithm
    measured = [i for i, v in enumerate(algorithm.get("bound_variance", [])) if v is not None]
    if not measured:
        return None

    def column(name: str) -> list[float]:
        values = algorithm.get(name, [None] * len(result))
        return [float(v) for i in measured if (v := values[i]) is not None]

    variances = column("bound_variance")
    budgets = [
        planned_budget(
            agent_profile(run, result.agents[i]).budget, (planned or {}).get(result.agents[i])
        )
        for i in measured
    ]
    second_moment = max(column("bound_second_moment"))
    secants = column("bound_smoothness")
    smoothness = max(secants) if secants else None
    grad_norms = column("bound_grad_norm_sq")
    record: dict[str, Any] = {
        "agents": len(measured),
        "variance_mean": sum(variances) / len(variances),
        "second_moment": second_moment,
        "grad_norm_sq_mean": sum(grad_norms) / len(measured),
        "smoothness": smoothness,
    }
    terms = theorem1_terms(
        gap=1.0,
        step_size=run.algo.step_size,
        smoothness=smoothness or 0.0,
        second_moment=second_moment,
        variances=variances,
        local_iters=[b.local_iters for b in budgets],
        batch_sizes=[b.batch_size for b in budgets],
        rounds=run.rounds,
    )
    record["optimisation_per_unit_gap"] = terms.optimisation
    if smoothness is not None:
        record.update(
            local_drift=terms.local_drift,
            variance=terms.variance,
            heterogeneity=terms.heterogeneity,
            step_size_ok=terms.step_size_ok,
        )
    return record
