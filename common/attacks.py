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

Every random draw comes from the agent's (seed, agent, round) stream, so attacks are as
reproducible as honest work, in one process or many.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import torch

from fedhpg.common.config import AttackConfig
from fedhpg.common.policies import ActionSampler
from fedhpg.common.rollout import TrajectoryBatch

UPDATE_ATTACKS = ("zero_gradient", "random_noise", "sign_flip")
SAMPLING_ATTACKS = ("reward_flip", "random_action")


def attack_of(attack: AttackConfig, agent_index: int) -> str:
    """The attack agent ``agent_index`` carries out ('none' for an honest agent)."""
    return attack.kind if agent_index in attack.agents else "none"


def corrupt_update(
    kind: str,
    start: torch.Tensor,
    honest: torch.Tensor,
    attack: AttackConfig,
    rng: np.random.Generator,
) -> torch.Tensor:
    """The θ_k an attacker sends instead of ``honest`` (computed from θ̃ = ``start``)."""
    delta = honest - start
    if kind == "zero_gradient":
        return start.clone()
    if kind == "sign_flip":
        return start - attack.sign_flip_scale * delta
    if kind == "random_noise":
        spread = float(delta.max() - delta.min()) if delta.numel() else 0.0
        noise = rng.uniform(-1.0, 1.0, size=delta.shape) * attack.noise_scale * spread
        return start + delta + torch.from_numpy(noise.astype(np.float32))
    return honest


def corrupt_batch(kind: str, batch: TrajectoryBatch) -> TrajectoryBatch:
    """The batch an attacker learns from: negated rewards for ``reward_flip``."""
    if kind == "reward_flip":
        return dataclasses.replace(batch, rewards=-batch.rewards)
    return batch


def random_action_sampler(space: gym.Space, policy_sampler: ActionSampler) -> ActionSampler:
    """Uniform actions from ``space`` (a bounded Box or Discrete), with the policy's
    log-probabilities of them (what the attacker's gradient is computed from)."""

    if isinstance(space, gym.spaces.Discrete):
        start, n = int(space.start), int(space.n)

        def act(obs: np.ndarray, rng: np.random.Generator, greedy: bool) -> np.ndarray:
            return start + rng.integers(n, size=(int(obs.shape[0]),))

    elif isinstance(space, gym.spaces.Box) and space.is_bounded():
        low, high = space.low.astype(np.float32), space.high.astype(np.float32)

        def act(obs: np.ndarray, rng: np.random.Generator, greedy: bool) -> np.ndarray:
            draws = rng.random((obs.shape[0], *low.shape), dtype=np.float32)
            return low + draws * (high - low)

    else:
        raise ValueError(f"random actions need a Discrete or bounded Box space, got {space}")
    return ActionSampler(act, policy_sampler.log_prob)
