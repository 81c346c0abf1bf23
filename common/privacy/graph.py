"""Who masks with whom in a secure round, and how many shares rebuild a secret (SecAgg+'s
graph, Bell et al., CCS 2020), derived from what the round must withstand.

**The graph.** Each agent masks its input with, and gives shares of its two secrets to, k
neighbours: every other agent (the complete graph of SecAgg) where the round is small, else
its k nearest on a ring of the agents (a Harary graph H(n, k)). The ring's order is drawn from
:func:`graph_seed`, a hash of the round and of every participant's fresh round mask key: no
party can know it before all of those keys are fixed, so nobody can arrange in advance to be a
target's neighbours (a ring in a public order let nine colluders chosen beforehand surround a
target). A party that sees the others' keys before choosing its own (a server with one
colluding agent) can try many keys; each try is one fresh draw of the graph, so this
multiplies the failure bounds below by the number of tries.

**The threshold.** t of an agent's k neighbours' shares rebuild a secret. What a round of n
agents must withstand is stated as two fractions of them: ``corruption`` γ (agents that
collude with the server and hand it everything they hold; a server that deviates from the
protocol may also ask different agents different questions) and ``dropout`` δ (agents that
stop answering, besides the colluders, who may stop too). An agent's input is exposed when the
colluders among its neighbours reach 2t − k (honest neighbours answer once a round, so a
server asking half of them for one secret and half for the other gets t shares of each only
when c + (k − c)/2 ≥ t), or when its honest neighbours' graph falls apart; the round fails
when more than k − t of an agent's neighbours stop answering. With colluders and drop-outs
placed at random by the graph's draw, each is a hypergeometric tail; :func:`plan_graph` takes
the smallest k (and the smallest t for it) with

- P[some input exposed] ≤ 2^-40 (union bound over the n agents, plus the ring being cut
  twice by runs of k/2 removed agents), and
- P[the round fails] ≤ 2^-20 (a failed round is skipped, not adopted).

A round of at most :data:`COMPLETE_UP_TO` agents uses the complete graph, where the same
conditions hold for every placement of the colluders and drop-outs, not just with high
probability.
"""

from __future__ import annotations

import functools
import hashlib
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from fedhpg.common.configuration.settings.privacy import SecAggConfig

PRIVACY_BITS = 40
"""P[some input exposed] ≤ 2^-PRIVACY_BITS in a round (Bell et al.'s σ)."""
CORRECTNESS_BITS = 20
"""P[a round fails from drop-outs] ≤ 2^-CORRECTNESS_BITS (Bell et al.'s η)."""
COMPLETE_UP_TO = 64
"""Rounds of at most this many agents use the complete graph: every agent masks with every
other (cost per agent grows with n, the guarantee holds for any placement)."""


class GraphError(ValueError):
    """A round whose size cannot meet the stated tolerance with any graph."""


@dataclass(frozen=True)
class Tolerance:
    """What a secure round must withstand, as fractions of its n agents."""

    corruption: float
    """γ: agents colluding with the server."""
    dropout: float
    """δ: agents that stop answering during the round (colluders may stop as well)."""

    def colluders(self, n: int) -> int:
        return math.floor(self.corruption * n + 1e-9)

    def silent(self, n: int) -> int:
        """The most agents that may not answer: drop-outs and colluders."""
        return min(n - 1, math.floor((self.corruption + self.dropout) * n + 1e-9))


@dataclass(frozen=True)
class GraphPlan:
    """A round's graph: k neighbours each, t shares rebuild a secret, and the bounds met."""

    agents: int
    neighbours: int
    """k (n − 1: the complete graph)."""
    threshold: int
    """t."""
    exposure: float
    """An upper bound on P[some agent's input is exposed] in the round."""
    failure: float
    """An upper bound on P[the round fails] from drop-outs."""

    @property
    def complete(self) -> bool:
        return self.neighbours >= self.agents - 1


def _tail(population: int, marked: int, draws: int, at_least: int) -> float:
    """P[X ≥ at_least] for X hypergeometric: ``draws`` of ``population`` with ``marked``."""
    if at_least <= 0:
        return 1.0
    if at_least > min(marked, draws):
        return 0.0
    from scipy.stats import hypergeom  # the privacy extra's dependency (dp-accounting's)

    return float(hypergeom(population, marked, draws).sf(at_least - 1))


def _ring_cut(agents: int, removed: int, neighbours: int) -> float:
    """A bound on P[the ring H(n, k) minus ``removed`` random agents is disconnected]: two
    runs of k/2 consecutive removed agents, union over their starting places."""
    if removed < neighbours:
        return 0.0
    pairs = math.comb(removed, neighbours) * agents * agents
    return min(1.0, pairs / math.comb(agents, neighbours))


def bounds(agents: int, neighbours: int, threshold: int, tolerance: Tolerance) -> GraphPlan:
    """The exposure and failure bounds of ``threshold``-of-``neighbours`` in a round of
    ``agents`` (the complete graph: 0 or 1, for the worst placement)."""
    k, t = neighbours, threshold
    colluders, silent = tolerance.colluders(agents), tolerance.silent(agents)
    if k >= agents - 1:
        exposure = 1.0 if colluders >= 2 * t - k or colluders >= t else 0.0
        failure = 1.0 if silent > k - t else 0.0
    else:
        others = agents - 1
        exposure = min(
            1.0,
            agents * _tail(others, colluders, k, min(t, 2 * t - k)) + _ring_cut(agents, silent, k),
        )
        failure = min(1.0, agents * _tail(others, silent, k, k - t + 1))
    return GraphPlan(agents=agents, neighbours=k, threshold=t, exposure=exposure, failure=failure)


def _meets(plan: GraphPlan) -> bool:
    return plan.exposure <= 2.0**-PRIVACY_BITS and plan.failure <= 2.0**-CORRECTNESS_BITS


def _smallest_threshold(agents: int, neighbours: int, tolerance: Tolerance) -> GraphPlan | None:
    """The smallest t whose exposure bound holds at ``neighbours``, if its failure bound
    holds too (a larger t only fails more often)."""
    k = neighbours
    t = k // 2 + 1
    if k < agents - 1:  # start near the tail's quantile instead of at k/2 + 1
        from scipy.stats import hypergeom

        quantile = hypergeom(agents - 1, tolerance.colluders(agents), k).isf(
            2.0**-PRIVACY_BITS / agents
        )
        if math.isfinite(quantile):
            t = max(t, math.ceil((k + int(quantile)) / 2) - 1)
    while t <= k:
        plan = bounds(agents, k, t, tolerance)
        if plan.exposure <= 2.0**-PRIVACY_BITS:
            return plan if _meets(plan) else None
        t += 1
    return None


def _fewest_neighbours(agents: int, tolerance: Tolerance) -> GraphPlan | None:
    """The smallest even k < n − 1 with a threshold that meets ``tolerance`` (a doubling
    search, then bisection: a larger k only narrows the tails)."""
    others = agents - 1
    largest = others - 1 - (others - 1) % 2
    high, found = 4, None
    while high <= largest:
        found = _smallest_threshold(agents, high, tolerance)
        if found is not None or high == largest:
            break
        high = min(2 * high, largest)
    if found is None:
        return None
    low = high // 2  # infeasible (or below 4)
    while high - low > 2:
        middle = (low + high) // 2
        middle -= middle % 2
        plan = _smallest_threshold(agents, middle, tolerance)
        if plan is not None:
            high, found = middle, plan
        else:
            low = middle
    return found


@functools.lru_cache(maxsize=256)
def plan_graph(
    agents: int,
    tolerance: Tolerance,
    neighbours: int | None = None,
    threshold: float | None = None,
) -> GraphPlan:
    """The graph of a round of ``agents`` that meets ``tolerance``: the complete graph up to
    :data:`COMPLETE_UP_TO` agents, else the fewest neighbours that do. ``neighbours`` (k) and
    ``threshold`` (t = ⌊threshold · k⌋ + 1) fix either choice; GraphError when the result
    does not meet the tolerance, saying what would."""
    if agents < 2:
        return GraphPlan(agents=agents, neighbours=0, threshold=0, exposure=0.0, failure=0.0)
    others = agents - 1
    k = others if neighbours is None else min(others, neighbours + neighbours % 2)
    if threshold is not None:
        plan = bounds(agents, k, min(math.floor(threshold * k) + 1, k), tolerance)
        if _meets(plan):
            return plan
    elif neighbours is not None or agents <= COMPLETE_UP_TO:
        if (found := _smallest_threshold(agents, k, tolerance)) is not None:
            return found
    else:
        if (found := _fewest_neighbours(agents, tolerance)) is not None:
            return found
        if (found := _smallest_threshold(agents, others, tolerance)) is not None:
            return found
    raise GraphError(_why(agents, k, threshold, tolerance))


def _why(agents: int, neighbours: int, threshold: float | None, tolerance: Tolerance) -> str:
    colluders, silent = tolerance.colluders(agents), tolerance.silent(agents)
    what = (
        f"a round of {agents} agents with {neighbours} neighbours each"
        + (f" and threshold {threshold:g}" if threshold is not None else "")
        + f" cannot both hide every input from a server with {colluders} colluding agents "
        f"(corruption {tolerance.corruption:g}) and complete with {silent} of them silent "
        f"(corruption + dropout {tolerance.corruption + tolerance.dropout:g})"
    )
    if threshold is not None or neighbours < agents - 1:
        try:
            fit = plan_graph(agents, tolerance)
        except GraphError:
            pass
        else:
            fits = f"t = {fit.threshold} of k = {fit.neighbours}"
            return (
                f"{what}; {fits} would (leave privacy.secagg.threshold and "
                "privacy.secagg.neighbours unset)"
            )
    return f"{what}; lower privacy.secagg.corruption or privacy.secagg.dropout"


def graph_seed(round_index: int, mask_keys: Mapping[int, bytes]) -> bytes:
    """The ring's order: SHA-256 of the round and every participant's (index, round mask
    public key), in index order. Known only once every key is fixed."""
    digest = hashlib.sha256(b"fedhpg secagg graph" + struct.pack("<q", round_index))
    for agent in sorted(mask_keys):
        digest.update(struct.pack("<q", agent) + mask_keys[agent])
    return digest.digest()


def neighbour_graph(
    participants: Sequence[int], neighbours: int, seed: bytes
) -> dict[int, tuple[int, ...]]:
    """Each participant's neighbours: every other one (k ≥ n − 1), or its k nearest on a ring
    of the participants in the order drawn from ``seed``."""
    people = sorted(participants)
    count = len(people)
    if neighbours >= count - 1:
        return {u: tuple(v for v in people if v != u) for u in people}
    ring = sorted(people, key=lambda u: hashlib.sha256(seed + struct.pack("<q", u)).digest())
    half = neighbours // 2
    graph: dict[int, tuple[int, ...]] = {}
    for position, u in enumerate(ring):
        near = {ring[(position + step) % count] for step in range(-half, half + 1)} - {u}
        graph[u] = tuple(sorted(near))
    return graph


def round_plan(settings: SecAggConfig, agents: int) -> GraphPlan:
    """The plan of a round of ``agents`` under ``privacy.secagg``: what both the server and
    every agent derive from the same settings (GraphError: the settings cannot meet their
    own tolerance at that size)."""
    tolerance = Tolerance(corruption=settings.corruption, dropout=settings.dropout)
    return plan_graph(agents, tolerance, settings.neighbours, settings.threshold)
