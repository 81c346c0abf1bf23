"""The ``attack`` section: Byzantine agents for robustness experiments (applied by
:mod:`fedhpg.common.learning.attacks`; the kinds are
:data:`fedhpg.common.configuration.vocabularies.ATTACKS`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from fedhpg.common.configuration.settings.checks import (
    check_choice,
    check_int,
    check_number,
    require,
)
from fedhpg.common.configuration.vocabularies import ATTACKS


@dataclass(kw_only=True)
class AttackConfig:
    """Byzantine agents, for robustness experiments only (off by default).

    The attacks FedPG-BR evaluates, applied by the attacking agents themselves: the server is
    never told who attacks.
    """

    kind: str = "none"
    """'none', 'zero_gradient' (send θ̃ back), 'random_noise' (add uniform noise of
    ``noise_scale`` × the update's range), 'sign_flip' (send −``sign_flip_scale`` × the
    update), 'reward_flip' (learn from negated rewards), 'random_action' (act uniformly at
    random while sampling), or an attack a plugin registers in ``vocabularies.ATTACKS``
    (``fedhpg.common.configuration``)."""
    agents: list[int] = field(default_factory=list)
    """Indices of the attacking agents."""
    sign_flip_scale: float = 2.5
    """'sign_flip': the update sent is −scale × the honest one (FedPG-BR: 2.5)."""
    noise_scale: float = 3.0
    """'random_noise': noise U(−1, 1) × scale × (max − min of the honest update) (FedPG-BR: 3)."""


def validate_attack(attack: AttackConfig, num_agents: int) -> None:
    check_choice(attack.kind, "attack.kind", ATTACKS)
    for i, index in enumerate(attack.agents):
        check_int(index, f"attack.agents[{i}]", low=0)
        require(
            index < num_agents,
            f"attack.agents[{i}]",
            f"got {index}, must be < agents.num_agents={num_agents}",
        )
    require(
        len(set(attack.agents)) == len(attack.agents),
        "attack.agents",
        f"lists an agent twice: {attack.agents}",
    )
    check_number(attack.sign_flip_scale, "attack.sign_flip_scale", low=0.0)
    check_number(attack.noise_scale, "attack.noise_scale", low=0.0)
