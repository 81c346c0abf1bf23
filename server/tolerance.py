"""A robust rule's tolerance, checked per aggregated set: at start and in every round's record.

A robust rule (:meth:`~fedhpg.server.strategies.Strategy.tolerance`) survives a number of
arbitrary rows among the m rows it aggregates, not among the K agents of the federation:
``median`` ⌈m/2⌉ − 1, ``trimmed_mean`` ⌊βm⌋. m is K only when every agent's update is
aggregated; with participation sampling it is ``per_round`` (and every attacker can be drawn
in one round), with a trace the sparsest round's count, under a deadline as few as
``server.min_agents``. Buffered rounds aggregate a robust rule over every agent's latest
update (:func:`fedhpg.server.buffered.buffer_rows`), so m = K there.

:func:`tolerance_shortfall` compares the smallest set's tolerance with what the run must
tolerate (``strategy.tolerate``, else the attackers ``attack.agents`` lists, at least one);
``strategy.tolerance_check`` says whether a shortfall refuses the run or warns. Each round's
record carries the set actually aggregated and its tolerance (``strategy.aggregated``,
``strategy.tolerates`` in ``metrics.jsonl``).
"""

from __future__ import annotations

from typing import Protocol

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.server.participation import smallest_participation


class RobustRule(Protocol):
    """What the check asks of a strategy (:class:`fedhpg.server.strategies.Strategy` is one)."""

    @property
    def name(self) -> str:
        """The rule's name in messages."""
        ...

    def tolerance(self, rows: int) -> int | None:
        """How many arbitrary rows among ``rows`` it survives (None: it claims none)."""
        ...


def smallest_set(run: RunConfig) -> tuple[int, str]:
    """The fewest rows a round of ``run`` may aggregate, and the setting that makes it so."""
    policy = ROUND_POLICIES.get(run.server.round_policy)
    if policy.asynchronous:
        return run.agents.num_agents, "buffered rounds aggregate every agent's latest update"
    rows, why = smallest_participation(run)
    if policy.quorum and run.server.min_agents < rows:
        rows = run.server.min_agents
        why = f"server.round_policy={run.server.round_policy} with server.min_agents={rows}"
    return rows, why


def to_tolerate(run: RunConfig) -> tuple[int, str]:
    """How many arbitrary rows every set must survive, and why."""
    if run.strategy.tolerate is not None:
        return run.strategy.tolerate, f"strategy.tolerate={run.strategy.tolerate}"
    if run.attack.kind != "none" and run.attack.agents:
        count = len(run.attack.agents)
        return count, f"attack.agents lists {count}, and every one can be in one set"
    return 1, "a robust rule should survive one"


def tolerance_shortfall(run: RunConfig, strategy: RobustRule) -> str | None:
    """Why ``strategy`` cannot keep its robustness in ``run``'s smallest set, or None (also
    for a rule that claims none, such as the mean)."""
    rows, where = smallest_set(run)
    tolerates = strategy.tolerance(rows)
    if tolerates is None:
        return None
    needed, why = to_tolerate(run)
    if tolerates >= needed:
        return None
    return (
        f"strategy={strategy.name} tolerates {tolerates} arbitrary update(s) in a set of {rows} "
        f"({where}), fewer than {needed} ({why})"
    )


REMEDY = (
    "aggregate more agents per round, set strategy.tolerate, or strategy.tolerance_check=warn "
    "to run anyway"
)
