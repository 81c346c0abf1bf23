"""The ``policy`` and ``eval`` sections: the policy network, and how the unified policy is
evaluated.
"""

from __future__ import annotations

from dataclasses import dataclass, field

LOG_STDS = ("state_independent", "state_dependent")


@dataclass(kw_only=True)
class PolicyConfig:
    """How to build the policy network for the run's spaces."""

    name: str = "auto"
    """'auto' (the built-in policy that fits the spaces: tabular, a CNN for images, else the
    MLP the actions take), a registered name ('tabular', 'mlp_categorical', 'gaussian_mlp',
    'mlp_multi_categorical', 'mlp_multi_binary', 'cnn', a plugin's), or a dotted path
    'package.module:Class' to a fedhpg Policy subclass."""
    hidden: list[int] = field(default_factory=lambda: [64, 64])
    """Hidden layer widths of the MLP policies and of the CNN's head (ignored by the tabular
    policy)."""
    log_std: str = "state_independent"
    """Gaussian policies: 'state_independent' or 'state_dependent' log σ."""
    init_log_std: float = -0.5
    """Gaussian policies: initial log σ."""


@dataclass(kw_only=True)
class EvalConfig:
    """How the unified policy is evaluated in every agent's environment."""

    every: int = 5
    """Evaluate every E rounds (and after the last round)."""
    episodes: int = 20
    """Episodes per environment."""
    greedy: bool = True
    """Greedy (argmax / mean action) evaluation; False samples from the policy."""
    horizon: int | None = None
    """Episode step limit when evaluating; None = the training horizon (``env.horizon``).
    FedPG-BR trains HalfCheetah with H=500 but validates over up to 1000 steps."""
    stop_at: float | None = None
    """Stop the run after an evaluation whose mean return over the agents reaches this target
    (a complete run: summary.json's ``stopped_early`` names the round); None = run every
    round."""
