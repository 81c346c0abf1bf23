"""The open choices of a run's settings: attacks, estimators, baselines, clocks, round policies.

Each is a :class:`~fedhpg.common.configuration.registry.Registry` of small frozen entries that
declare what the rest of the package asks of a name (an attack: whether it changes how its agent
samples, how it poisons the update it sends; a clock: whether it counts work instead of measuring
it), so code reads the entry, never the name. The package's own choices are registered here, in
the order the messages list them; a plugin module (``plugins=[my.module]``) registers more::

    from fedhpg.common.configuration.vocabularies import ATTACKS, Attack

    ATTACKS.register("double")(Attack(corrupt=lambda u: u.start + 2.0 * u.delta))

Pure Python (no torch): the config validates names against these registries in every process.
An attack's ``corrupt`` receives tensors, and uses only their methods.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from fedhpg.common.configuration.registry import Registry

if TYPE_CHECKING:
    import torch


class AttackScales(Protocol):
    """The scales of the run's ``attack`` section an attack may read
    (:class:`~fedhpg.common.configuration.settings.attack.AttackConfig`)."""

    sign_flip_scale: float
    noise_scale: float


@dataclass(frozen=True)
class UpdateToCorrupt:
    """What an attack that poisons its update sees of one attacking agent's round."""

    start: torch.Tensor
    """θ̃, the round's starting parameters [d]."""
    delta: torch.Tensor
    """Δ_k = θ_k − θ̃, the update the agent would honestly send [d]."""
    options: AttackScales
    """The run's ``attack`` section (its scales)."""
    uniforms: Callable[[], torch.Tensor]
    """U[0, 1) draws, one per coordinate, from the agent's (seed, agent, round) attack
    stream: an attack's randomness is as reproducible as honest work."""


@dataclass(frozen=True)
class Attack:
    """An ``attack.kind``: what the attacking agents do differently from honest ones."""

    acts_randomly: bool = False
    """The agent acts uniformly at random while sampling (and computes its gradient for
    those actions)."""
    flips_rewards: bool = False
    """The agent learns from negated rewards."""
    corrupt: Callable[[UpdateToCorrupt], torch.Tensor] | None = None
    """The θ_k the agent sends instead of the honest one; None sends the honest one."""

    @property
    def samples_differently(self) -> bool:
        """Whether the attack changes the agent's sampling (the compiled CPU backend, which
        samples honestly only, then leaves the agent to the torch engine)."""
        return self.acts_randomly or self.flips_rewards

    @property
    def poisons_update(self) -> bool:
        return self.corrupt is not None


def _zero_gradient(update: UpdateToCorrupt) -> torch.Tensor:
    return update.start


def _sign_flip(update: UpdateToCorrupt) -> torch.Tensor:
    return update.start - update.options.sign_flip_scale * update.delta


def _random_noise(update: UpdateToCorrupt) -> torch.Tensor:
    delta = update.delta
    spread = float(delta.max() - delta.min()) if delta.shape[0] else 0.0
    noise = (2.0 * update.uniforms() - 1.0) * update.options.noise_scale * spread
    return update.start + delta + noise.to(delta.device, delta.dtype)


ATTACKS: Registry[Attack] = Registry("attack", "attack.kind", in_order=True)
ATTACKS.register("none")(Attack())
ATTACKS.register("zero_gradient")(Attack(corrupt=_zero_gradient))
ATTACKS.register("random_noise")(Attack(corrupt=_random_noise))
ATTACKS.register("sign_flip")(Attack(corrupt=_sign_flip))
ATTACKS.register("reward_flip")(Attack(flips_rewards=True))
ATTACKS.register("random_action")(Attack(acts_randomly=True))


@dataclass(frozen=True)
class Estimator:
    """An ``algo.estimator``: how a trajectory's rewards weigh its actions' score functions."""

    per_step: bool
    """Each action is credited with the rewards from its own step on (GPOMDP, eq. 6), which
    ``algo.reward_to_go=from_step``, ``algo.normalize=episode``, FedPG-BR and per-decision
    importance weights need; False: with the whole trajectory's return (REINFORCE, eq. 5)."""


ESTIMATORS: Registry[Estimator] = Registry("estimator", "algo.estimator", in_order=True)
ESTIMATORS.register("reinforce")(Estimator(per_step=False))
ESTIMATORS.register("gpomdp")(Estimator(per_step=True))


@dataclass(frozen=True)
class Baseline:
    """An ``algo.baseline``: what is subtracted from the rewards an action is credited with."""

    subtracts_mean: bool
    """The mean over the agent's other trajectories (per step for a per-step estimator) is
    subtracted; False: nothing is."""


BASELINES: Registry[Baseline] = Registry("baseline", "algo.baseline", in_order=True)
BASELINES.register("none")(Baseline(subtracts_mean=False))
BASELINES.register("mean")(Baseline(subtracts_mean=True))


@dataclass(frozen=True)
class Clock:
    """An ``agents.clock``: how an emulated device's time is kept."""

    counts_work: bool
    """Emulated time is priced from the work counted (steps, backward passes, bytes sent), the
    same on any machine, and nobody sleeps; False: the work's measured time, with sleeps for
    the emulated delays."""


CLOCKS: Registry[Clock] = Registry("clock", "agents.clock", in_order=True)
CLOCKS.register("measured")(Clock(counts_work=False))
CLOCKS.register("counted")(Clock(counts_work=True))


@dataclass(frozen=True)
class RoundPolicy:
    """A ``server.round_policy``: when the server closes a round."""

    quorum: bool = False
    """A round may close with ``server.min_agents`` accepted answers, once every live agent
    has answered or ``server.round_deadline_s`` has passed; the missing are left out."""
    asynchronous: bool = False
    """No synchronous rounds: agents' updates are buffered and applied as they arrive
    (FedBuff-style, ``server.buffer_size``, ``server.max_staleness``)."""

    @property
    def waits_for_every_agent(self) -> bool:
        """Every asked agent must answer: a lost one that does not rejoin within
        ``server.rejoin_timeout_s`` ends the run."""
        return not self.quorum and not self.asynchronous


ROUND_POLICIES: Registry[RoundPolicy] = Registry(
    "round policy", "server.round_policy", in_order=True
)
ROUND_POLICIES.register("wait_all")(RoundPolicy())
ROUND_POLICIES.register("deadline")(RoundPolicy(quorum=True))
ROUND_POLICIES.register("buffered")(RoundPolicy(asynchronous=True))
