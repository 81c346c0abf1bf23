"""Theorem 1 as a planner: per-agent budgets (B_k, τ_k) that minimise the eq. 7 bound within a
total emulated-time budget. Pure maths: no wire, no processes, no torch.

Time model. Agent k's round takes ``τ_k B_k c_k + o_k`` emulated seconds, with ``c_k`` the
seconds of one trajectory (sampling and its gradient) on its device and ``o_k`` the round's
fixed cost (its two messages). The round ends with its slowest agent (Algorithm 1 waits for
every update), so a round takes R = max_k (τ_k B_k c_k + o_k) and a budget of ``total_s``
allows T = floor(total_s / R) rounds. Every agent's own round time is ≤ R by construction: no
agent is planned past the round everyone waits for.

Objective. Eq. 7 with T = T(R), through :func:`fedhpg.common.learning.bounds.theorem1_terms` (its
readings: τ̄ = mean τ_k, V = 1, one M). Written out, the bound is K (A + Σ_k h_k(τ_k, B_k)) /
Σ_k τ_k with A = 2 gap / (γ T) and h_k agent k's share of terms 2–4 (α_A and α_B are means over
k, so term 4 splits per agent too). Only the denominator couples the agents.

Search (what is exact). For one R, each agent's best B for a given τ is the largest that fits
(h_k falls with B), and the ratio over the agents' choices of τ is minimised exactly by
Dinkelbach's iteration: with λ the current bound, each agent minimises h_k − λ τ_k/K alone, and
λ decreases until it is a fixed point, the exact optimum over that finite set. The optimal plan's
R is one of the values τ B c_k + o_k, so searching every such value is exact; past
``max_round_times`` candidates a geometric grid of them is searched instead (a heuristic: a
plan between two grid points can be missed).

Step-size condition. γ < 1/L does not depend on the plan: where it fails no plan satisfies the
theorem and :attr:`Plan.step_size_ok` says so (the plan still minimises the formula). The second
condition, γ < 2(K + τ̄)/(L K α_B), does: a plan that breaks it is replaced by the best plan with
τ_max one lower, until one holds (all τ_k = 1 make α_B = 0, so one always does). That descent is
a heuristic: it can miss a plan that keeps some agents at the larger τ.

Theorem 2 (FedHPGVR, eq. 10): see :func:`theorem2_shape`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from fedhpg.common.learning.bounds import Theorem1Terms, theorem1_terms


@dataclass(frozen=True, kw_only=True)
class Constants:
    """Theorem 1's constants, as estimated (``algo.bound_estimates``) or supplied."""

    gap: float
    """J(θ*) − J(θ_0), the first term's numerator (no run knows it: a stated reading)."""
    step_size: float
    """γ."""
    smoothness: float
    """L."""
    second_moment: float
    """M."""
    variances: tuple[float, ...]
    """σ_k², one per agent."""


@dataclass(frozen=True, kw_only=True)
class Limits:
    """The box each agent's budget is chosen in."""

    batch_min: int = 2
    batch_max: int = 64
    local_iters_max: int = 8
    max_round_times: int = 4000
    """Most candidate round times searched exactly (see the module docstring)."""

    def __post_init__(self) -> None:
        if not 1 <= self.batch_min <= self.batch_max:
            raise ValueError(
                f"need 1 ≤ batch_min ≤ batch_max, got {self.batch_min}, {self.batch_max}"
            )
        if self.local_iters_max < 1:
            raise ValueError(f"local_iters_max must be ≥ 1, got {self.local_iters_max}")
        if self.max_round_times < 2:
            raise ValueError(f"max_round_times must be ≥ 2, got {self.max_round_times}")


@dataclass(frozen=True, kw_only=True)
class Plan:
    """Integer budgets per agent, the round time they give, and the bound."""

    batch_sizes: tuple[int, ...]
    local_iters: tuple[int, ...]
    agent_round_s: tuple[float, ...]
    """Each agent's own emulated round time, τ_k B_k c_k + o_k."""
    round_s: float
    """R, the slowest agent's round time."""
    rounds: int
    """T = floor(total_s / R)."""
    terms: Theorem1Terms
    step_size_ok: bool
    """Both of Theorem 1's step-size conditions hold for this plan."""

    @property
    def bound(self) -> float:
        return self.terms.total


def _per_agent_share(
    constants: Constants, variance: float, tau: int, batch: int, num_agents: int
) -> float:
    """h_k: agent k's part of terms 2–4 of eq. 7 times τ̄ (so the bound is (A + Σh_k)/τ̄)."""
    gl = constants.step_size * constants.smoothness
    cubic = tau * (tau - 1) * (2 * tau - 1)
    drift = gl * gl * variance * cubic / (6 * batch)
    spread = gl * tau * tau * variance / batch
    heterogeneity = gl * constants.second_moment * (gl * cubic / 6 + (1 - gl / 2) * tau * (tau - 1))
    return (drift + spread + heterogeneity) / num_agents


def _largest_batch(
    round_s: float, tau: int, seconds_per_trajectory: float, overhead_s: float, limits: Limits
) -> int | None:
    """The largest B in the box whose round fits in ``round_s`` at τ, or None."""
    room = round_s - overhead_s
    if room <= 0:
        return None
    # A relative tolerance so that a candidate R built from (τ, B) admits that B again.
    fits = math.floor(room / (tau * seconds_per_trajectory) * (1 + 1e-12))
    batch = min(limits.batch_max, fits)
    return batch if batch >= limits.batch_min else None


def _best_within(
    round_s: float,
    rounds: int,
    constants: Constants,
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
    limits: Limits,
    tau_max: int,
) -> tuple[list[int], list[int]] | None:
    """Exact best (τ_k, B_k) of every agent with each round ≤ ``round_s`` (Dinkelbach)."""
    k = len(seconds_per_trajectory)
    options: list[list[tuple[int, int, float]]] = []
    for agent in range(k):
        mine = []
        for tau in range(1, tau_max + 1):
            batch = _largest_batch(
                round_s, tau, seconds_per_trajectory[agent], overhead_s[agent], limits
            )
            if batch is not None:
                share = _per_agent_share(constants, constants.variances[agent], tau, batch, k)
                mine.append((tau, batch, share))
        if not mine:
            return None
        options.append(mine)
    first = 2 * constants.gap / (constants.step_size * rounds)

    def ratio(choice: list[tuple[int, int, float]]) -> float:
        return k * (first + sum(c[2] for c in choice)) / sum(c[0] for c in choice)

    choice = [mine[0] for mine in options]  # τ = 1 everywhere: a feasible start
    value = ratio(choice)

    def best_option(mine: list[tuple[int, int, float]], lam: float) -> tuple[int, int, float]:
        # Dinkelbach's step: h_k − λ τ_k / K, each agent alone.
        return min(mine, key=lambda c: c[2] - lam * c[0] / k)

    while True:
        better = [best_option(mine, value) for mine in options]
        new_value = ratio(better)
        if new_value >= value * (1 - 1e-12):
            break
        choice, value = better, new_value
    return [c[0] for c in choice], [c[1] for c in choice]


def _candidate_round_times(
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
    limits: Limits,
    tau_max: int,
    total_s: float,
) -> list[float]:
    values = sorted(
        {
            tau * batch * c + o
            for c, o in zip(seconds_per_trajectory, overhead_s, strict=True)
            for tau in range(1, tau_max + 1)
            for batch in range(limits.batch_min, limits.batch_max + 1)
            if tau * batch * c + o <= total_s
        }
    )
    if len(values) <= limits.max_round_times:
        return values
    n = limits.max_round_times
    return [values[round(i * (len(values) - 1) / (n - 1))] for i in range(n)]


def plan_budgets(
    *,
    constants: Constants,
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
    total_s: float,
    limits: Limits | None = None,
) -> Plan:
    """The plan minimising eq. 7 within ``total_s`` emulated seconds (module docstring).

    Raises ValueError when not even one round of the smallest budgets fits in ``total_s``.
    """
    limits = limits or Limits()
    k = len(seconds_per_trajectory)
    if not (k == len(overhead_s) == len(constants.variances)) or k == 0:
        raise ValueError("speeds, overheads and variances need one entry per agent")
    if any(c <= 0 for c in seconds_per_trajectory) or any(o < 0 for o in overhead_s):
        raise ValueError("seconds per trajectory must be > 0 and overheads ≥ 0")
    if total_s <= 0 or constants.step_size <= 0 or constants.gap < 0:
        raise ValueError("the time budget and step size must be > 0, the gap ≥ 0")
    tau_max = limits.local_iters_max
    while True:
        best: Plan | None = None
        for round_s in _candidate_round_times(
            seconds_per_trajectory, overhead_s, limits, tau_max, total_s
        ):
            rounds = math.floor(total_s / round_s * (1 + 1e-12))
            found = _best_within(
                round_s, rounds, constants, seconds_per_trajectory, overhead_s, limits, tau_max
            )
            if found is None:
                continue
            plan = _plan_of(constants, seconds_per_trajectory, overhead_s, total_s, *found)
            if best is None or plan.bound < best.bound:
                best = plan
        if best is None:
            slowest = max(
                limits.batch_min * c + o
                for c, o in zip(seconds_per_trajectory, overhead_s, strict=True)
            )
            raise ValueError(
                f"no round of batch_size ≥ {limits.batch_min} fits in {total_s:g} emulated s "
                f"(the slowest agent needs {slowest:g} s)"
            )
        second_condition = _second_condition_holds(constants, best.local_iters)
        if second_condition or tau_max == 1:
            return best
        tau_max -= 1


def plan_for_rounds(
    *,
    constants: Constants,
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
    total_s: float,
    rounds: int,
    limits: Limits | None = None,
) -> Plan:
    """The plan minimising eq. 7 when T is fixed: ``rounds`` rounds within ``total_s``.

    A run whose length is set (``agents.plan=theorem1`` re-planning the rounds left) gives
    every round total_s / rounds. With T fixed the first term is too, and a longer round only
    lets each agent take a larger batch, so the longest round that fits is the best: one round
    time is searched (exactly, as in :func:`plan_budgets`, with its step-size rule).

    Raises ValueError when not even the smallest budgets fit in total_s / rounds."""
    limits = limits or Limits()
    if rounds < 1:
        raise ValueError(f"rounds must be ≥ 1, got {rounds}")
    if total_s <= 0 or constants.step_size <= 0 or constants.gap < 0:
        raise ValueError("the time budget and step size must be > 0, the gap ≥ 0")
    round_s = total_s / rounds
    tau_max = limits.local_iters_max
    while True:
        found = _best_within(
            round_s, rounds, constants, seconds_per_trajectory, overhead_s, limits, tau_max
        )
        if found is None:
            slowest = max(
                limits.batch_min * c + o
                for c, o in zip(seconds_per_trajectory, overhead_s, strict=True)
            )
            raise ValueError(
                f"no round of batch_size ≥ {limits.batch_min} fits in {round_s:g} emulated s "
                f"(the slowest agent needs {slowest:g} s)"
            )
        local_iters, batch_sizes = found
        slowest_round = max(
            agent_round_seconds(local_iters, batch_sizes, seconds_per_trajectory, overhead_s)
        )
        plan = _plan_of(
            constants,
            seconds_per_trajectory,
            overhead_s,
            slowest_round * rounds,
            local_iters,
            batch_sizes,
        )
        if _second_condition_holds(constants, plan.local_iters) or tau_max == 1:
            return plan
        tau_max -= 1


def agent_round_seconds(
    local_iters: Sequence[int],
    batch_sizes: Sequence[int],
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
) -> tuple[float, ...]:
    """Each agent's round, τ_k B_k c_k + o_k emulated seconds (the module's time model)."""
    return tuple(
        t * b * c + o
        for t, b, c, o in zip(
            local_iters, batch_sizes, seconds_per_trajectory, overhead_s, strict=True
        )
    )


def _second_condition_holds(constants: Constants, local_iters: Sequence[int]) -> bool:
    k = len(local_iters)
    alpha_b = sum(t * (t - 1) for t in local_iters) / k
    if alpha_b == 0 or constants.smoothness <= 0:
        return True
    tau_bar = sum(local_iters) / k
    return constants.step_size < 2 * (k + tau_bar) / (constants.smoothness * k * alpha_b)


def _plan_of(
    constants: Constants,
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
    total_s: float,
    local_iters: Sequence[int],
    batch_sizes: Sequence[int],
) -> Plan:
    """A plan for given budgets: its round times, rounds and bound (also to score others)."""
    agent_round_s = agent_round_seconds(
        local_iters, batch_sizes, seconds_per_trajectory, overhead_s
    )
    round_s = max(agent_round_s)
    rounds = math.floor(total_s / round_s * (1 + 1e-12))
    if rounds < 1:
        raise ValueError(f"a round takes {round_s:g} s, more than the {total_s:g} s budget")
    terms = theorem1_terms(
        gap=constants.gap,
        step_size=constants.step_size,
        smoothness=constants.smoothness,
        second_moment=constants.second_moment,
        variances=constants.variances,
        local_iters=local_iters,
        batch_sizes=batch_sizes,
        rounds=rounds,
    )
    return Plan(
        batch_sizes=tuple(batch_sizes),
        local_iters=tuple(local_iters),
        agent_round_s=agent_round_s,
        round_s=round_s,
        rounds=rounds,
        terms=terms,
        step_size_ok=terms.step_size_ok,
    )


def score_budgets(
    *,
    constants: Constants,
    seconds_per_trajectory: Sequence[float],
    overhead_s: Sequence[float],
    total_s: float,
    batch_sizes: Sequence[int],
    local_iters: Sequence[int],
) -> Plan:
    """Any given budgets as a :class:`Plan`: the bound the planner would give them."""
    return _plan_of(
        constants, seconds_per_trajectory, overhead_s, total_s, local_iters, batch_sizes
    )


@dataclass(frozen=True, kw_only=True)
class Theorem2Shape:
    """Eq. 10's three terms with its unknown constants factored out (see :func:`theorem2_shape`)."""

    optimisation: float
    """2 K gap / (T γ (K − 1 − β)): fully determined once β is chosen."""
    mini_batch_per_zeta: float
    """(βγL + 1)(K − 1 − β)/(Kβ) Σ_k N / b_k: term 2 divided by ζ."""
    snapshot_per_xi: float
    """(βγL + 1)(K − 1 − β)/(Kβ) Σ_k N / B_k: term 3 divided by ξ."""
    step_size_ok: bool
    """γ < 1/L."""


def theorem2_shape(
    *,
    gap: float,
    step_size: float,
    smoothness: float,
    rounds: int,
    inner_steps: int,
    batch_sizes: Sequence[int],
    mini_batch_sizes: Sequence[int],
    beta: float,
) -> Theorem2Shape:
    """Eq. 10 (FedHPGVR) as far as it can be evaluated.

    What cannot be estimated, and why: ζ and ξ are "positive constants depending on W, M, G and
    F" with no formula in the paper, so terms 2 and 3 are only known per unit of ζ and ξ; W (the
    importance-weight variance bound, Assumption 5) and G, F (Assumption 2) are suprema over all
    policies that no run measures. β appears in eq. 10 undefined; the terms need 0 < β < K − 1,
    and the caller chooses it (a stated reading, never estimated). With ζ, ξ unknown the
    trade-off between T, B_k and b_k is not determined, so no FedHPGVR planner is built on it:
    only the shape, which says each term falls with its own parameter (Remark 4).
    """
    k = len(batch_sizes)
    if k != len(mini_batch_sizes) or k < 2:
        raise ValueError("one batch_size and mini_batch_size per agent, at least 2 agents")
    if not 0 < beta < k - 1:
        raise ValueError(f"β must lie in (0, K − 1) = (0, {k - 1}), got {beta}")
    if rounds < 1 or step_size <= 0 or inner_steps < 1:
        raise ValueError("rounds, inner_steps must be ≥ 1 and the step size > 0")
    weight = (beta * step_size * smoothness + 1) * (k - 1 - beta) / (k * beta)
    return Theorem2Shape(
        optimisation=2 * k * gap / (rounds * step_size * (k - 1 - beta)),
        mini_batch_per_zeta=weight * sum(inner_steps / b for b in mini_batch_sizes),
        snapshot_per_xi=weight * sum(inner_steps / b for b in batch_sizes),
        step_size_ok=smoothness <= 0 or step_size < 1 / smoothness,
    )
