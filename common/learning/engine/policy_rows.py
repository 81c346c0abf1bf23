"""One policy architecture, many agents' θ: the policy's own maths applied per row.

θ is a [A, d] tensor, row a the flat parameter vector of agent a (the order of
``policy.parameters()``, as the server averages it). Every operation is the policy's own
``act_with`` / ``log_prob_with`` on the rows' parameters: in one call over all rows where the
policy's maths broadcast over rows (``Policy.rows_batched``: the built-in ones), else vmapped
over rows with ``torch.func`` (any other policy, a plugin's included, batched without a line
written for it). Gradients are autograd's: the loss of row a depends on row a's parameters
alone, so one backward pass gives every row its own gradient, and a row's numbers do not
depend on the other rows of the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch.func import grad, vmap

from fedhpg.common.learning.policies import Params, Policy


class PolicyRows:
    """Per-row calls of ``policy``'s maths (its own parameters serve only as shapes)."""

    def __init__(self, policy: Policy, device: torch.device) -> None:
        self.policy = policy.to(device)
        self.device = device
        named = list(self.policy.named_parameters())
        self.names = [name for name, _ in named]
        self.shapes = [tuple(p.shape) for _, p in named]
        self.sizes = [p.numel() for _, p in named]
        self.num_params = sum(self.sizes)
        self.noise_size = int(policy.noise_size)
        self.batched = bool(policy.rows_batched)

    def params(self, theta: torch.Tensor) -> Params:
        """The rows' parameters as views of ``theta`` [A, d]."""
        rows = theta.shape[0]
        pieces = torch.split(theta, self.sizes, dim=1)
        return {
            name: piece.reshape(rows, *shape)
            for name, piece, shape in zip(self.names, pieces, self.shapes, strict=True)
        }

    def flatten(self, grads: Params) -> torch.Tensor:
        """Per-row gradients (name → [A, *shape]) as [A, d] rows, in θ's order."""
        return torch.cat([grads[name].reshape(grads[name].shape[0], -1) for name in self.names], 1)

    def act(
        self, theta: torch.Tensor, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        """Actions of ``obs`` [A, C, *obs_shape] (C copies per row) from ``noise``
        [A, C, noise_size] (None: greedy)."""
        params = self.params(theta)
        with torch.no_grad():
            if self.batched:
                return self.policy.act_with(params, obs, noise)
            if noise is None:
                return vmap(lambda p, o: self.policy.act_with(p, o, None))(params, obs)
            return vmap(self.policy.act_with)(params, obs, noise)

    def log_probs(
        self, theta: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor
    ) -> torch.Tensor:
        """log π_θa(actions | obs) per row: obs [A, R, *obs_shape], actions [A, R, ...] →
        [A, R]."""
        params = self.params(theta)
        with torch.no_grad():
            if self.batched:
                return self.policy.log_prob_with(params, obs, actions)
            return vmap(self.policy.log_prob_with)(params, obs, actions)

    def score_gradients(
        self,
        theta: torch.Tensor,
        obs: torch.Tensor,
        actions: torch.Tensor,
        coefficients: torch.Tensor,
    ) -> torch.Tensor:
        """Σ_r coef[a, r] ∇_θ log π_θa(actions[a, r] | obs[a, r]) for every row a, [A, d]."""
        if not self.batched:
            grads = vmap(grad(self._surrogate))(self.params(theta), obs, actions, coefficients)
            return self.flatten(grads)
        leaf = theta.detach().requires_grad_(True)
        with torch.enable_grad():
            log_probs = self.policy.log_prob_with(self.params(leaf), obs, actions)
            loss = (coefficients.to(log_probs.dtype) * log_probs).sum()
            (gradient,) = torch.autograd.grad(loss, leaf)
        return gradient

    def _surrogate(
        self, params: Params, obs: torch.Tensor, actions: torch.Tensor, coef: torch.Tensor
    ) -> torch.Tensor:
        log_probs = self.policy.log_prob_with(params, obs, actions)
        return (coef.to(log_probs.dtype) * log_probs).sum()


def chunked(rows: int, per_row: int, budget: int, call: Callable[[slice], Any]) -> list[Any]:
    """``call(block)`` over consecutive blocks of rows, each holding at most ``budget``
    elements (``per_row`` each; at least one row)."""
    size = max(budget // max(per_row, 1), 1)
    return [call(slice(start, min(start + size, rows))) for start in range(0, rows, size)]
