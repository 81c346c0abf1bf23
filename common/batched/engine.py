"""FedHPG (Algorithm 1) for a group of agents in lockstep: the batched :class:`AgentGroup`.

Each local iteration, every agent that still has iterations left (τ_k > i) samples its B_k
trajectories (one lockstep rollout for all), the GPOMDP/REINFORCE gradients of all of them
are computed in stacked products, and each takes its ascent step (plain or Adam, clipped to
``algo.grad_clip``) on its own row of θ [A, d]. Agent k's numbers depend on agent k alone,
so a group of one (the one-agent process), a host of 500 and the in-process pool give it
the same θ bit for bit (see :mod:`fedhpg.common.batched.mlp` for how).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextlib import closing
from typing import Any

import numpy as np
import torch

from fedhpg.common.batched import coefficients as coef
from fedhpg.common.batched import mlp
from fedhpg.common.batched.agents import EngineAgents
from fedhpg.common.batched.maths import PolicyMaths, maths_for
from fedhpg.common.batched.sampler import Batches, block_order, rollout
from fedhpg.common.batched.scheduler import RoundTiming, run_round
from fedhpg.common.bounds import gradient_moments
from fedhpg.common.components import planned_budget
from fedhpg.common.config import RunConfig
from fedhpg.common.group import Budgets, GroupHook
from fedhpg.common.local import SmoothnessProbe, bound_stats
from fedhpg.common.types import EvaluationStats, LocalResult
from fedhpg.common.worker import IterationWork, Stream, random_stream
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.multi import make_multi_batch_env

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
"""common/optim.py's AdamAscent defaults."""
PER_TRAJECTORY_FLOATS = 1 << 22
"""``algo.bound_estimates``: per-trajectory gradients held at once (16 MB of float32)."""


def ascend(
    optimizer: str,
    step_size: float,
    theta: np.ndarray,
    gradient: np.ndarray,
    moments: tuple[np.ndarray, np.ndarray],
    done: np.ndarray,
) -> None:
    """θ += the ascent direction, in place on rows of agents: plain steps (the paper) or Adam
    (``moments`` = its first and second moments, updated in place, fresh every round;
    ``done`` = each row's steps taken before this one)."""
    if optimizer == "sgd":
        theta += np.float32(step_size) * gradient
        return
    first, second = moments
    beta1, beta2 = ADAM_BETAS
    first *= np.float32(beta1)
    first += np.float32(1 - beta1) * gradient
    second *= np.float32(beta2)
    second += np.float32(1 - beta2) * (gradient * gradient)
    steps = (done + 1)[:, None]
    first_hat = first / (1 - beta1**steps).astype(np.float32)
    second_hat = second / (1 - beta2**steps).astype(np.float32)
    theta += np.float32(step_size) * first_hat / (np.sqrt(second_hat) + np.float32(ADAM_EPS))


class BatchedFedHPG(EngineAgents):
    """The agents ``variants`` of a FedHPG run with the MLP categorical policy."""

    def __init__(self, run: RunConfig, variants: Mapping[int, EnvVariant], shape: mlp.MLPShape):
        super().__init__(run, variants, shape)
        self.maths: PolicyMaths = maths_for(run.algo.engine, run.algo.device)
        """Where the policy maths run (``algo.engine``, ``algo.device``)."""

    # -- training -------------------------------------------------------------------------

    def train(
        self,
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        *,
        on_iteration: GroupHook | None = None,
        budgets: Budgets | None = None,
    ) -> dict[int, LocalResult]:
        algo = self.run.algo
        planned = budgets or {}
        chosen = {k: planned_budget(self.budget(k), planned.get(k)) for k in agents}
        batch = {k: chosen[k].batch_size for k in agents}
        iters = {k: chosen[k].local_iters for k in agents}
        order = block_order(agents, batch)
        rngs = [random_stream(self.run.seed, k, round_index, Stream.TRAIN) for k in order]
        params = np.repeat(theta.detach().numpy().astype(np.float32)[None, :], len(order), 0)
        moments = (np.zeros_like(params), np.zeros_like(params))
        # algo.bound_estimates: each agent's first batch (at θ̃) and second (the secant for L)
        # measured before its step; the counts say which of an agent's batches this is
        measured_batches = np.zeros(len(order), dtype=np.int64)
        bounds: dict[int, dict[str, float]] = {}
        probes: dict[int, SmoothnessProbe] = {}

        def gradient_step(batches: Batches, rows: np.ndarray, done: np.ndarray) -> np.ndarray:
            layers = self.maths.unflatten(self.shape, params[rows])
            active = [order[i] for i in rows]
            found: list[dict[str, float]] = []
            if algo.bound_estimates:  # off: nothing added to the gradient step
                wanted = measured_batches[rows] < 2
                if wanted.any():
                    found = self._bound_statistics(batches, layers, active, wanted)
            gradient = self._gradient(batches, layers, active)
            for j in np.flatnonzero(wanted) if found else ():
                i = int(rows[j])
                if measured_batches[i] == 0:
                    bounds[i] = dict(found[j])
                if found[j]:
                    probe = probes.setdefault(i, SmoothnessProbe())
                    noise = found[j]["bound_variance"] / batch[order[i]]
                    probe.add(torch.from_numpy(params[i]), torch.from_numpy(gradient[j]), noise)
                    bounds[i].update(probe.stats())
                measured_batches[i] += 1
            clipped = self._clip(gradient)
            stepped = params[rows]
            first, second = moments[0][rows], moments[1][rows]
            ascend(algo.optimizer, algo.step_size, stepped, gradient, (first, second), done)
            params[rows], moments[0][rows], moments[1][rows] = stepped, first, second
            return clipped

        def on_batch(row: int, iteration: int, env_steps: int, compute_s: float) -> None:
            if on_iteration is not None:
                work = IterationWork(iteration, compute_s, env_steps, env_steps)
                on_iteration(order[row], work)

        env = make_multi_batch_env([self.variants[k] for k in order], [batch[k] for k in order])
        timing = RoundTiming()
        # An agent whose steps diverge samples from NaN logits until its round ends; the server
        # rejects its update and says why, so numpy's warnings would only repeat it.
        with closing(env), np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            tallies = run_round(
                env,
                self.shape,
                params,
                rngs,
                [self.horizons[k] for k in order],
                [iters[k] for k in order],
                gradient_step,
                on_batch,
                timing,
                self.maths,
            )
        total_steps = max(sum(t.env_steps for t in tallies), 1)
        results = {}
        for i, k in enumerate(order):
            share = tallies[i].env_steps / total_steps
            # the engine's split of the group's time, this agent's share (by steps)
            tallies[i].algorithm = {
                "engine_sample_s": timing.sample_s * share,
                "engine_gradient_s": timing.gradient_s * share,
                **bounds.get(i, {}),
            }
            results[k] = tallies[i].result(torch.from_numpy(params[i].copy()))
        return results

    def _gradient(self, batches: Batches, layers: Any, active: list[int]) -> np.ndarray:
        """(1/B_k) Σ_b g(τ_b) of every active agent, [A, d]."""
        gammas = np.array([self.gammas[k] for k in active])
        c = coef.coefficients(
            batches,
            gammas,
            estimator=self.run.algo.estimator,
            baseline=self.run.algo.baseline,
            reward_to_go=self.run.algo.reward_to_go,
            normalize=self.run.algo.normalize,
        )
        c /= np.diff(batches.offsets)[batches.owner][None, :]
        chunks = mlp.pack_rows(
            batches.row_agent,
            batches.obs,
            batches.actions,
            c.reshape(-1)[batches.row_cell].astype(np.float32),
            len(active),
        )
        return self.maths.score_gradient(self.shape, layers, chunks)

    def _bound_statistics(
        self, batches: Batches, layers: Any, active: list[int], wanted: np.ndarray
    ) -> list[dict[str, float]]:
        """Theorem 1's constants of every active agent's batch (``common/bounds.py``), from
        per-trajectory gradients: the same kernel with one owner per trajectory instead of per
        agent, so an agent's figures depend on its own rows alone, like its θ. In blocks of
        agents, so the [trajectories, d] matrix stays small."""
        gammas = np.array([self.gammas[k] for k in active])
        c = coef.coefficients(
            batches,
            gammas,
            estimator=self.run.algo.estimator,
            baseline=self.run.algo.baseline,
            reward_to_go=self.run.algo.reward_to_go,
            normalize=self.run.algo.normalize,
        )
        width = c.shape[1]
        column = batches.row_cell % width  # the row's trajectory (its copy's column)
        order = np.argsort(column, kind="stable")  # by trajectory, time order kept
        column, cells = column[order], batches.row_cell[order]
        coefficient = c.reshape(-1)[cells].astype(np.float32)
        columns_per_block = max(PER_TRAJECTORY_FLOATS // self.shape.num_params, 1)
        measured: list[dict[str, float]] = []
        agent = 0
        while agent < len(active):
            if not wanted[agent]:
                measured.append({})
                agent += 1
                continue
            last = agent + 1  # whole agents wanted, as many as the block holds
            while (
                last < len(active)
                and wanted[last]
                and batches.offsets[last + 1] - batches.offsets[agent] <= columns_per_block
            ):
                last += 1
            low, high = int(batches.offsets[agent]), int(batches.offsets[last])
            r0, r1 = np.searchsorted(column, [low, high])
            chunks = mlp.pack_rows(
                column[r0:r1] - low,
                batches.obs[order[r0:r1]],
                batches.actions[order[r0:r1]],
                coefficient[r0:r1],
                high - low,
            )
            owners = self.maths.select(layers, batches.owner[low:high])
            rows = self.maths.score_gradient(self.shape, owners, chunks)
            for i in range(agent, last):
                start, stop = int(batches.offsets[i]) - low, int(batches.offsets[i + 1]) - low
                if stop - start < 2:
                    measured.append({})
                    continue
                moments = gradient_moments(torch.from_numpy(rows[start:stop]))
                measured.append(bound_stats(moments))
            agent = last
        return measured

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
        layers = self.maths.unflatten(self.shape, params)
        env = make_multi_batch_env([self.variants[k] for k in order], [episodes] * len(order))
        rngs = [random_stream(self.run.seed, k, round_index, Stream.EVALUATE) for k in order]
        horizons = [self.run.eval.horizon or self.horizons[k] for k in order]
        with closing(env), np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            rollouts = rollout(
                env, layers, rngs, horizons, greedy=self.run.eval.greedy, maths=self.maths
            )
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
