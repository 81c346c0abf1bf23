"""FedHPG (Algorithm 1) for a group of agents in lockstep: the batched :class:`AgentGroup`.

Each local iteration, every agent that still has iterations left (τ_k > i) samples its B_k
trajectories (one lockstep rollout for all), the GPOMDP/REINFORCE gradients of all of them
are computed in stacked products, and each takes its ascent step (plain or Adam, clipped to
``algo.grad_clip``) on its own row of θ [A, d]. Agent k's numbers depend on agent k alone,
so a group of one (the one-agent process), a host of 500 and the in-process pool give it
the same θ bit for bit (see :mod:`fedhpg.common.batched.mlp` for how).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from fedhpg.common.batched import coefficients as coef
from fedhpg.common.batched import mlp
from fedhpg.common.batched.sampler import Rollouts, block_order, rollout
from fedhpg.common.components import agent_profile
from fedhpg.common.config import RunConfig
from fedhpg.common.group import GroupHook
from fedhpg.common.types import EvaluationStats, LocalResult, UpdateStats
from fedhpg.common.variants import discount, training_horizon
from fedhpg.common.worker import IterationWork, Stream, random_stream
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.multi import make_multi_batch_env

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
"""common/optim.py's AdamAscent defaults."""


def ascend(
    optimizer: str,
    step_size: float,
    theta: np.ndarray,
    gradient: np.ndarray,
    moments: tuple[np.ndarray, np.ndarray] | None,
    iteration: int,
) -> None:
    """θ += the ascent direction, in place on rows of agents: plain steps (the paper) or Adam
    (``moments`` = its first and second moments, updated in place; fresh every round)."""
    if optimizer == "sgd":
        theta += np.float32(step_size) * gradient
        return
    assert moments is not None
    first, second = moments
    beta1, beta2 = ADAM_BETAS
    first *= np.float32(beta1)
    first += np.float32(1 - beta1) * gradient
    second *= np.float32(beta2)
    second += np.float32(1 - beta2) * (gradient * gradient)
    steps = iteration + 1
    first_hat = first / np.float32(1 - beta1**steps)
    second_hat = second / np.float32(1 - beta2**steps)
    theta += np.float32(step_size) * first_hat / (np.sqrt(second_hat) + np.float32(ADAM_EPS))


LENGTH_RATIO = 1.25
"""Agents whose batch lengths are within this ratio share one padded block for the gradient."""


def _length_groups(lengths: np.ndarray) -> list[np.ndarray]:
    """Agent positions grouped by batch length (each group's longest ≤ LENGTH_RATIO × its
    shortest); the grouping changes only the padding, never a result."""
    order = np.argsort(lengths, kind="stable")
    groups, start = [], 0
    for i in range(1, len(order) + 1):
        if i == len(order) or lengths[order[i]] > LENGTH_RATIO * lengths[order[start]]:
            groups.append(np.sort(order[start:i]))
            start = i
    return groups


class BatchedFedHPG:
    """The agents ``variants`` of a FedHPG run with the MLP categorical policy."""

    def __init__(self, run: RunConfig, variants: dict[int, EnvVariant], shape: mlp.MLPShape):
        self.run = run
        self.variants = variants
        self.shape = shape
        self.profiles = {k: agent_profile(run, k) for k in variants}
        self.gammas = {k: discount(run, v) for k, v in variants.items()}
        self.horizons = {k: training_horizon(run, v) for k, v in variants.items()}

    @property
    def indices(self) -> Sequence[int]:
        return sorted(self.variants)

    @property
    def num_params(self) -> int:
        return self.shape.num_params

    # -- training -------------------------------------------------------------------------

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        on_iteration: GroupHook | None = None,
    ) -> dict[int, LocalResult]:
        algo = self.run.algo
        budgets = {k: self.profiles[k].budget for k in agents}
        batch = {k: int(budgets[k].batch_size) for k in agents}  # type: ignore[attr-defined]
        iters = {k: int(budgets[k].local_iters) for k in agents}  # type: ignore[attr-defined]
        order = block_order(agents, batch)
        rngs = {k: random_stream(self.run.seed, k, round_index, Stream.TRAIN) for k in order}
        params = np.repeat(theta.detach().numpy().astype(np.float32)[None, :], len(order), 0)
        tally = {k: [0, 0, 0.0, 0.0, 0] for k in order}  # trajectories, steps, return, cpu, clips
        adam = algo.optimizer == "adam"
        first, second = np.zeros_like(params), np.zeros_like(params)
        for iteration in range(max(iters.values())):
            started = time.thread_time()
            rows = np.array([i for i, k in enumerate(order) if iters[k] > iteration])
            active = [order[i] for i in rows]
            layers = mlp.unflatten(self.shape, params[rows])
            env = make_multi_batch_env(
                [self.variants[k] for k in active], [batch[k] for k in active]
            )
            try:
                rollouts = rollout(
                    env, layers, [rngs[k] for k in active], [self.horizons[k] for k in active]
                )
            finally:
                env.close()
            gradient = self._gradient(rollouts, layers, active)
            clipped = self._clip(gradient)
            stepped = params[rows]
            moments = (first[rows], second[rows]) if adam else None
            ascend(algo.optimizer, algo.step_size, stepped, gradient, moments, iteration)
            params[rows] = stepped
            if moments is not None:
                first[rows], second[rows] = moments
            compute_s = time.thread_time() - started
            steps = rollouts.env_steps()
            returns = np.add.reduceat(coef.returns(rollouts), rollouts.offsets[:-1])
            total_steps = max(int(steps.sum()), 1)
            for a, k in enumerate(active):
                share = compute_s * int(steps[a]) / total_steps
                t = tally[k]
                t[0] += batch[k]
                t[1] += int(steps[a])
                t[2] += float(returns[a])
                t[3] += share
                t[4] += int(clipped[a])
                if on_iteration is not None:
                    on_iteration(k, IterationWork(iteration, share, int(steps[a]), int(steps[a])))
        results = {}
        for i, k in enumerate(order):
            trajectories, env_steps, return_sum, compute_s, clips = tally[k]
            results[k] = LocalResult(
                theta=torch.from_numpy(params[i].copy()),
                stats=UpdateStats(
                    trajectories=int(trajectories),
                    env_steps=int(env_steps),
                    train_return=float(return_sum) / max(int(trajectories), 1),
                    compute_s=float(compute_s),
                    grad_clipped=int(clips),
                ),
            )
        return results

    def _gradient(self, rollouts: Rollouts, layers: mlp.Layers, active: list[int]) -> np.ndarray:
        """(1/B_k) Σ_b g(τ_b) of every active agent, [A, d].

        Computed per group of agents of similar batch length T_k (each group padded to its
        longest, not to the longest of all: lengths differ by 10x and more)."""
        gradient = np.empty((len(active), self.shape.num_params), dtype=np.float32)
        gammas = np.array([self.gammas[k] for k in active])
        for agents in _length_groups(rollouts.lengths):
            sub = rollouts.subset(agents)
            c = coef.coefficients(
                sub, gammas[agents], estimator=self.run.algo.estimator,
                baseline=self.run.algo.baseline,
            )  # fmt: skip
            copies = np.diff(sub.offsets)
            c = c / copies[sub.owner][None, :]
            # the alive steps, agent by agent, each agent's in time-major order
            owner = np.broadcast_to(sub.owner, sub.alive.shape)[sub.alive]
            order = np.argsort(owner, kind="stable")
            chunks = mlp.pack_rows(
                owner[order],
                sub.obs[sub.alive][order],
                sub.actions[sub.alive][order],
                c[sub.alive][order].astype(np.float32),
                len(agents),
            )
            gradient[agents] = mlp.score_gradient(self.shape, mlp.select(layers, agents), chunks)
        return gradient

    def _clip(self, gradient: np.ndarray) -> np.ndarray:
        """Scale rows down to norm ``algo.grad_clip`` (Assumption 3); which rows were."""
        max_norm = self.run.algo.grad_clip
        clipped = np.zeros(len(gradient), dtype=bool)
        if max_norm is None:
            return clipped
        for i, row in enumerate(gradient):
            norm = float(np.sqrt(np.dot(row, row)))
            if norm > max_norm:
                row *= np.float32(max_norm / norm)
                clipped[i] = True
        return clipped

    # -- evaluation -----------------------------------------------------------------------

    def evaluate(
        self, round_index: int, theta: torch.Tensor, episodes: int, agents: Sequence[int]
    ) -> dict[int, EvaluationStats]:
        order = sorted(agents)
        params = np.repeat(theta.detach().numpy().astype(np.float32)[None, :], len(order), 0)
        layers = mlp.unflatten(self.shape, params)
        env = make_multi_batch_env([self.variants[k] for k in order], [episodes] * len(order))
        rngs = [random_stream(self.run.seed, k, round_index, Stream.EVALUATE) for k in order]
        horizons = [self.run.eval.horizon or self.horizons[k] for k in order]
        try:
            rollouts = rollout(env, layers, rngs, horizons, greedy=self.run.eval.greedy)
        finally:
            env.close()
        gammas = np.array([self.gammas[k] for k in order])
        undiscounted = coef.returns(rollouts)
        discounted = coef.returns(rollouts, gammas)
        lengths = rollouts.alive.sum(axis=0)
        stats = {}
        for a, k in enumerate(order):
            block = slice(rollouts.offsets[a], rollouts.offsets[a + 1])
            stats[k] = EvaluationStats(
                return_mean=float(undiscounted[block].mean()),
                return_std=float(undiscounted[block].std()),
                discounted_return_mean=float(discounted[block].mean()),
                success_rate=float(rollouts.success[block].mean()),
                length_mean=float(lengths[block].mean()),
                episodes=episodes,
            )
        return stats

    def close(self) -> None:
        pass
