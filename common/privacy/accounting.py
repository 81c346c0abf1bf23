"""(ε, δ) of a run's rounds, from Google's ``dp-accounting`` library.

Each round releases the clipped sum of the participating agents' updates with Gaussian noise
of multiplier σ (:mod:`.dp`): a Gaussian mechanism on the round's sample of agents, composed
over the rounds. How the sample is drawn decides the amplification and the neighbouring
relation the guarantee is stated for:

- every agent every round (``strategy.participation.mode=all``) or a trace (no randomness to
  amplify by): the Gaussian mechanism itself, adding or removing one agent;
- C of K agents drawn uniformly without replacement (``uniform``): the library's
  ``SampledWithoutReplacementDpEvent`` (Wang, Balle and Kasiviswanathan 2019), which holds for
  replacing one agent by another; replacing moves the clipped sum by up to 2C, so its noise
  multiplier is σ/2;
- each agent independently with probability q (:class:`Sampling` ``poisson``): Poisson
  subsampling, adding or removing one agent (DP-SGD's and DP-FedAvg's analyses).

Amplification by sampling holds only against a party that does not know the sample: the
sample must be drawn secretly and never written where that party reads
(:mod:`fedhpg.server.participation`). Against a party that knows it (``known=True``: the
server of ``dp_secagg``, which picks it), a round is the plain Gaussian mechanism for the agents
it drew and nothing for the others: an agent's guarantee composes only the rounds it took part
in, and the run reports the worst agent's (the same neighbouring relation: replacing one agent
moves a round's sum by 2C, multiplier σ/2; adding or removing one, by C).

The accountant is the library's RDP accountant (Mironov 2017, with its default orders) or its
privacy-loss-distribution accountant (``pld``; for the Gaussian and Poisson-subsampled cases).
Nothing here keeps state: a run's accounting is a function of (σ, the sampling, rounds so far),
so a checkpoint needs only the rounds it has accounted.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Literal

ACCOUNTANTS = ("rdp", "pld")
SamplingKind = Literal["all", "fixed", "poisson"]


@dataclass(frozen=True, kw_only=True)
class Sampling:
    """How a round's agents are drawn from the population of ``population`` agents."""

    kind: SamplingKind
    population: int
    sample: int = 0
    """``fixed``: agents per round (C)."""
    rate: float = 1.0
    """``poisson``: each agent's probability of taking part (q)."""

    @property
    def expected(self) -> float:
        """The expected number of participants per round (the average's public denominator)."""
        if self.kind == "fixed":
            return float(self.sample)
        if self.kind == "poisson":
            return self.rate * self.population
        return float(self.population)

    @property
    def relation(self) -> str:
        """The neighbouring relation the guarantee holds for."""
        return "replace one agent" if self.kind == "fixed" else "add or remove one agent"


class AccountingError(ValueError):
    """An accountant that cannot account the run's sampling (e.g. PLD without replacement)."""


def _library() -> Any:
    import dp_accounting  # imported where accounting is used: startup costs nothing otherwise

    return dp_accounting


def round_event(noise_multiplier: float, sampling: Sampling, *, known: bool = False) -> Any:
    """One round as a ``dp_accounting.DpEvent`` (``known``: against a party that knows the
    sample, for an agent in it)."""
    dp = _library()
    if known:
        # the sample is a public input: the Gaussian mechanism on the sum, whose sensitivity
        # is 2C to replacing one agent (multiplier σC / 2C), C to adding or removing one
        return dp.GaussianDpEvent(
            noise_multiplier / 2 if sampling.kind == "fixed" else noise_multiplier
        )
    if sampling.kind == "fixed":
        # replacing one agent moves the clipped sum by up to 2C: multiplier σC / 2C
        return dp.SampledWithoutReplacementDpEvent(
            sampling.population, sampling.sample, dp.GaussianDpEvent(noise_multiplier / 2)
        )
    gaussian = dp.GaussianDpEvent(noise_multiplier)
    if sampling.kind == "poisson" and sampling.rate < 1:
        return dp.PoissonSampledDpEvent(sampling.rate, gaussian)
    return gaussian


def make_accountant(kind: str, sampling: Sampling, *, known: bool = False) -> Any:
    """A fresh accountant of the library for ``sampling``'s neighbouring relation (``known``:
    a plain Gaussian per round, whose sensitivity :func:`round_event` scales for the relation)."""
    dp = _library()
    relation = (
        dp.NeighboringRelation.REPLACE_ONE
        if sampling.kind == "fixed" and not known
        else dp.NeighboringRelation.ADD_OR_REMOVE_ONE
    )
    if kind == "rdp":
        return dp.rdp.RdpAccountant(neighboring_relation=relation)
    if kind == "pld":
        if sampling.kind == "fixed" and not known:
            raise AccountingError(
                "the PLD accountant has no sampling without replacement: use accountant 'rdp' "
                "for strategy.participation.mode=uniform"
            )
        return dp.pld.PLDAccountant(neighboring_relation=relation)
    raise AccountingError(f"unknown accountant {kind!r}; known: {', '.join(ACCOUNTANTS)}")


@functools.lru_cache(maxsize=256)
def _round_rdp(noise_multiplier: float, sampling: Sampling, known: bool) -> tuple[Any, Any]:
    """The RDP orders and one round's RDP at each, as the library's accountant composes them:
    composition adds RDP, so t rounds are t times this (what the library's
    ``SelfComposedDpEvent`` computes, without recomputing the round's RDP for every t)."""
    accountant = make_accountant("rdp", sampling, known=known)
    accountant.compose(round_event(noise_multiplier, sampling, known=known))
    return accountant._orders, accountant._rdp.copy()  # checked against compose() in tests


def epsilon(
    noise_multiplier: float,
    sampling: Sampling,
    rounds: int,
    delta: float,
    kind: str = "rdp",
    *,
    known: bool = False,
) -> float:
    """ε after ``rounds`` rounds at ``delta`` (0 rounds: 0; σ = 0: infinite); ``known``:
    against a party that knows every round's sample, ``rounds`` being those the agent took
    part in (no amplification)."""
    if rounds <= 0:
        return 0.0
    if noise_multiplier <= 0:
        return float("inf")
    dp = _library()
    if kind == "rdp":
        orders, rdp = _round_rdp(noise_multiplier, sampling, known)
        return float(dp.rdp.rdp_privacy_accountant.compute_epsilon(orders, rounds * rdp, delta)[0])
    accountant = make_accountant(kind, sampling, known=known)
    event = round_event(noise_multiplier, sampling, known=known)
    accountant.compose(dp.SelfComposedDpEvent(event, rounds))
    return float(accountant.get_epsilon(delta))


@functools.lru_cache(maxsize=64)
def calibrate(
    target_epsilon: float,
    sampling: Sampling,
    rounds: int,
    delta: float,
    kind: str = "rdp",
    *,
    known: bool = False,
) -> float:
    """The smallest noise multiplier σ (to 1e-4 relative) whose ``rounds`` rounds spend at most
    ``target_epsilon`` at ``delta`` (``known``: against a party that knows the sample, for an
    agent drawn in every round): the library's own calibration (Brent's method)."""
    dp = _library()
    sigma = dp.calibrate_dp_mechanism(
        lambda: make_accountant(kind, sampling, known=known),
        lambda s: dp.SelfComposedDpEvent(round_event(s, sampling, known=known), rounds),
        target_epsilon,
        delta,
        bracket_interval=dp.LowerEndpointAndGuess(0.3 if kind == "pld" else 0.05, 1.0),
        tol=1e-5,
    )
    # Brent's tolerance may land just below the boundary: never report a σ over budget
    while epsilon(sigma, sampling, rounds, delta, kind, known=known) > target_epsilon:
        sigma *= 1 + 1e-4
    return float(sigma)


DELTA_CAP = 1e-5
"""The largest default δ, whatever the population."""


def default_delta(population: int) -> float:
    """δ = min(1/(10·K), 10⁻⁵): well below 1/K (a mechanism that published one random agent's
    data whole would meet δ = 1/K), and never above 10⁻⁵, the usual ceiling, for a small
    federation (1/K^1.1, DP-FedAvg's choice, is 0.22 for four agents)."""
    return min(1.0 / (10 * population), DELTA_CAP)
