"""The primitives an algorithm's loop needs, as a protocol: what a backend supplies.

Two implement it, chosen once per agent group (``common/learning/group.py``):

- :class:`~fedhpg.common.learning.engine.torch_backend.TorchBackend`: every policy, environment
  family and space, on ``algo.device`` (the CPU or a GPU), all rows stepped together;
- :class:`~fedhpg.common.learning.batched.backend.CompiledBackend`: the MLP categorical policy on
  CartPole variants on the CPU, in numba, an agent at a time (a sample with its keys one
  compiled call, its coefficients and gradients another).

The estimator's definition is torch's (``common/learning/estimators.py``, applied to a batch by
``common/learning/engine/estimate.py``); a backend's own form of it is held bit-equal to it by a
test. A backend's coefficients are in its own layout: only its own ``gradients`` and
``trajectory_gradients`` read them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

import torch

from fedhpg.common.learning.engine.estimate import EstimatorOptions
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.randomness import Purpose


class Draws(NamedTuple):
    """Whose random draws a sampling call makes: trajectory n of row a is keyed by (seed,
    ``agents[a]``, round, purpose, iteration, n)."""

    seed: int
    agents: torch.Tensor
    """[A] int64: each row's agent."""
    round_index: int
    purpose: Purpose
    iteration: int


class Backend(Protocol):
    """Sampling and the policy-gradient maths for rows of agents (θ rows [A, d])."""

    def keys(self, draws: Draws, counts: torch.Tensor) -> torch.Tensor:
        """The keys of trajectories 0 … ``counts[a]`` − 1 of each row a, row after row
        (:func:`~fedhpg.common.learning.randomness.trajectory_keys`)."""
        ...

    def sample(
        self,
        theta: torch.Tensor,
        counts: torch.Tensor,
        draws: Draws,
        horizons: torch.Tensor,
        agents: Sequence[int],
        *,
        greedy: bool,
    ) -> Trajectories:
        """``counts[a]`` ≥ 1 episodes of agent ``agents[a]`` at θ row ``theta[a]``, each of at
        most ``horizons[a]`` steps, each drawn from its own key (:meth:`keys`)."""
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

    def mean_gradients(
        self,
        theta: torch.Tensor,
        batch: Trajectories,
        options: EstimatorOptions,
        gammas: torch.Tensor,
        weights: torch.Tensor | None,
    ) -> torch.Tensor:
        """Each row's mean gradient of ``batch`` at ``theta`` with the estimator's
        :meth:`coefficients`, [A, d]: exactly :func:`defined_mean_gradients`, which a backend
        may compute in one call."""
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


def defined_mean_gradients(
    backend: Backend,
    theta: torch.Tensor,
    batch: Trajectories,
    options: EstimatorOptions,
    gammas: torch.Tensor,
    weights: torch.Tensor | None,
) -> torch.Tensor:
    """:meth:`Backend.mean_gradients` by its definition: (1/B_a) Σ_n Σ_t coef[t, n]
    ∇ log π_θa(a_t|s_t) over each row a's B_a trajectories, [A, d] float32, with the run's
    estimator (0 for a row without trajectories)."""
    sums = backend.gradients(theta, batch, backend.coefficients(batch, options, gammas, weights))
    return sums.div_(batch.counts.clamp_min(1).unsqueeze(1))
