"""The primitives an algorithm's loop needs, as a protocol: what a backend supplies.

Two implement it, chosen once per agent group (``common/learning/group.py``):

- :class:`~fedhpg.common.learning.engine.torch_backend.TorchBackend`: every policy, environment
  family and space, on ``algo.device`` (the CPU or a GPU), all rows stepped together;
- :class:`~fedhpg.common.learning.batched.backend.CompiledBackend`: the MLP categorical policy on
  CartPole variants on the CPU, in numba, fused per agent (sampling, coefficients and
  gradients a compiled call each).

The estimator's definition is torch's (``common/learning/estimators.py``, applied to a batch by
``common/learning/engine/estimate.py``); a backend's own form of it is held bit-equal to it by a
test. A backend's coefficients are in its own layout: only its own ``gradients`` and
``trajectory_gradients`` read them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch

from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.randomness import Purpose


class Backend(Protocol):
    """Sampling and the policy-gradient maths for rows of agents (θ rows [A, d])."""

    def keys(
        self,
        seed: int,
        agents: torch.Tensor,
        counts: torch.Tensor,
        round_index: int,
        purpose: Purpose,
        iteration: int,
    ) -> torch.Tensor:
        """The keys of trajectories 0 … ``counts[a]`` − 1 of each agent ``agents[a]``, row
        after row (:func:`~fedhpg.common.learning.randomness.trajectory_keys`)."""
        ...

    def sample(
        self,
        theta: torch.Tensor,
        counts: torch.Tensor,
        keys: torch.Tensor,
        horizons: torch.Tensor,
        agents: Sequence[int],
        *,
        greedy: bool,
    ) -> Trajectories:
        """One episode per key: ``counts[a]`` ≥ 1 of agent ``agents[a]`` at θ row ``theta[a]``,
        each of at most ``horizons[a]`` steps."""
        ...

    def coefficients(
        self,
        batch: Trajectories,
        options: EstimatorOptions,
        gammas: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        """The estimator's coefficients of ``batch`` in the backend's layout (``gammas`` [A]
        each row's discount; ``weights`` [N] or [T, N] importance weights, or None)."""
        ...

    def gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """Σ_n Σ_t coef[t, n] ∇ log π_θa(a_t|s_t) per row a, [A, d]."""
        ...

    def trajectory_gradients(
        self, theta: torch.Tensor, batch: Trajectories, coefficients: torch.Tensor
    ) -> torch.Tensor:
        """g(τ_n | θ_{owner(n)}) of every trajectory, [N, d]."""
        ...

    def log_probs(self, theta: torch.Tensor, batch: Trajectories) -> torch.Tensor:
        """log π_θa(a_t|s_t) of every alive step, [T, N] float64 (0 elsewhere)."""
        ...

    def prepare(self) -> None:
        """Build now what the first round would (an agent host prepares at registration)."""
        ...

    def close(self) -> None: ...
