"""Byzantine agents for robustness experiments: the attacks FedPG-BR evaluates (Section 5).

Only agents listed in ``attack.agents`` attack, and only when ``attack.kind`` is not 'none'
(the default). In FedHPG an agent sends θ_k, so an attack on "the gradient" acts on the update
Δ_k = θ_k − θ̃ the agent would honestly send:

- ``zero_gradient``: Δ = 0 (θ̃ is sent back);
- ``random_noise``: Δ + U(−1, 1) · noise_scale · (max Δ − min Δ), element-wise (FedPG-BR adds
  such noise to each parameter tensor's gradient, with scale 3; here over the flat vector);
- ``sign_flip``: −sign_flip_scale · Δ (FedPG-BR: −2.5 × the gradient, so 3 attackers of 10
  turn a plain mean backwards: 7 − 3 · 2.5 < 0);
- ``reward_flip``: the agent learns from negated rewards;
- ``random_action``: the agent acts uniformly at random while sampling (a faulty actuator),
  and computes its gradient for those actions.

Each is an entry of :data:`~fedhpg.common.configuration.vocabularies.ATTACKS`, which declares what
it does; a plugin registers more. Every random draw comes from the agent's (seed, agent, round)
stream, so attacks are as reproducible as honest work, in one process or many.
"""

from __future__ import annotations

import torch

from fedhpg.common.configuration.settings.attack import AttackConfig
from fedhpg.common.configuration.vocabularies import ATTACKS, Attack, UpdateToCorrupt
from fedhpg.common.learning.randomness import Purpose, trajectory_keys, uniforms

HONEST = ATTACKS.get("none")
"""What an agent that does not attack does."""


def attack_of(attack: AttackConfig, agent_index: int) -> Attack:
    """The attack agent ``agent_index`` carries out (:data:`HONEST` for an honest agent)."""
    return ATTACKS.get(attack.kind) if agent_index in attack.agents else HONEST


def corrupt_rows(
    attack: AttackConfig,
    start: torch.Tensor,
    honest: torch.Tensor,
    agents: list[int],
    *,
    seed: int,
    round_index: int,
) -> torch.Tensor:
    """The θ_k rows the agents send: ``honest`` [A, d] where the agent is honest or attacks
    its sampling, the corrupted update where it poisons its update (from θ̃ = ``start``, [d]
    of any float type).
    Random draws come from the agent's (seed, agent, round) attack stream."""
    if not attack.agents or not ATTACKS.get(attack.kind).poisons_update:
        return honest
    kinds = [attack_of(attack, k) for k in agents]
    if not any(kind.poisons_update for kind in kinds):
        return honest
    start = start.detach().to(torch.float32)
    sent = honest.clone()
    delta = honest - start
    for row, kind in enumerate(kinds):
        if kind.corrupt is None:
            continue

        def draws(agent: int = agents[row]) -> torch.Tensor:
            key = trajectory_keys(
                seed,
                torch.tensor([agent]),
                round_index,
                Purpose.ATTACK,
                0,
                torch.zeros(1, dtype=torch.int64),
            )
            return uniforms(key, torch.arange(delta.shape[1], device=key.device))

        update = UpdateToCorrupt(start=start, delta=delta[row], options=attack, uniforms=draws)
        sent[row] = kind.corrupt(update)
    return sent
