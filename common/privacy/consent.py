"""What an agent accepts of a private round the server asks for: the clip and the noise come
from the agent's own ``privacy`` settings (which it holds as the server does: the group is
agreed, not adopted), so a server that asks for less noise, or another clip, is refused.

The agent derives the least noise it may add from what it knows without the server:

- ``privacy.noise_multiplier`` given: that σ;
- ``privacy.budget_against=server``: the σ that spends the budget against a party that knows
  the sample, for an agent drawn in every round (no amplification: the same whatever the
  server's sampling, which the agent need not know);
- otherwise the budget is against readers of the released model, with amplification by a
  sample that the server draws: σ depends on the server's sampling, which the agent cannot
  check, and no floor binds the server (docs/privacy.md says so).

Its share of the noise is at least σ·C/√s, s = :func:`~.secagg.noise_shares` of the round's
participants (with adaptive clipping the update's own multiplier is above σ, so σ is a floor
there too), C the clip the round uses: the agent's own, or under adaptive clipping the one the
server tracks (a larger C also scales the noise the agent adds, so it costs no privacy).
"""

from __future__ import annotations

import math

from fedhpg.common.configuration.settings.privacy import PrivacyConfig
from fedhpg.common.privacy import accounting
from fedhpg.common.privacy.accounting import Sampling
from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.privacy.secagg import noise_shares

RELATIVE_SLACK = 1e-9
"""Float round-off allowed between the server's figures and the agent's own."""


def least_noise_multiplier(settings: PrivacyConfig, population: int, rounds: int) -> float | None:
    """The σ an agent holds the server to (None: no floor it can check)."""
    if settings.noise_multiplier is not None:
        return settings.noise_multiplier
    if settings.budget_against != "server" or settings.epsilon is None:
        return None
    delta = settings.delta if settings.delta is not None else accounting.default_delta(population)
    sampling = Sampling(kind="all", population=population)
    return accounting.calibrate(settings.epsilon, sampling, rounds, delta, known=True)


def refusal(
    settings: PrivacyConfig,
    asked: RoundPrivacy,
    *,
    participants: int,
    population: int,
    rounds: int,
) -> str | None:
    """Why the agent refuses to contribute as ``asked`` in a round of ``participants``, or
    None where the request agrees with its own settings."""
    if settings.mode not in ("secagg", "dp_secagg"):
        return f"the server asks for a secure round, this agent runs privacy.mode={settings.mode}"
    if not math.isclose(asked.bound, settings.secagg.range, rel_tol=RELATIVE_SLACK):
        return f"range {asked.bound:g} asked, privacy.secagg.range is {settings.secagg.range:g}"
    if settings.mode == "secagg":
        return None
    if not settings.adaptive_clip and not math.isclose(
        asked.clip, settings.clip, rel_tol=RELATIVE_SLACK
    ):
        return f"clip {asked.clip:g} asked, privacy.clip is {settings.clip:g}"
    if not asked.clip > 0:
        return "no clip asked: an update's sensitivity would be unbounded"
    sigma = least_noise_multiplier(settings, population, rounds)
    if sigma is None:
        return None
    least = sigma * asked.clip / math.sqrt(noise_shares(settings.secagg, participants))
    if asked.noise_std < least * (1 - RELATIVE_SLACK):
        return (
            f"noise std {asked.noise_std:.4g} asked, below the {least:.4g} that σ = "
            f"{sigma:.4g} needs over {participants} participants"
        )
    return None
