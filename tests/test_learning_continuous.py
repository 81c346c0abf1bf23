"""A continuous-action family learns: FedHPG on HalfCheetah-v5 over a 100-step horizon (K=2,
B=16, τ=1, agents' plain steps of size 1 averaged and applied with server Adam, FedPG-BR's
arrangement) raises the greedy (mean-action) return far beyond the evaluation noise; the same
run with a server step size of 1e-12 (the config refuses exactly 0) fails the same check.

Threshold. The initial policy (mean action ≈ 0) has a greedy return of −0.5 to −0.2 with a std
of 0.46–0.95 over episodes (seeds 0–7); over 2 agents × 20 episodes the standard error of the
mean is ≈ 0.11, so the difference of two independent 40-episode evaluations has a standard
error of ≈ 0.16 (measured: the untrained policy's two evaluations differed by at most 0.2).
``MIN_GAIN`` = 5 is ≈ 30 such standard errors. After 40 rounds the gain was 12.7–160 over seeds
0–7 (seed 0, the one tested: 57.5), and 0.2 at most with the 1e-12 step size.

Settings chosen by measuring 8 seeds: plain local SGD (η = 1e-3 or 2e-3, τ = 2) gave gains from
−186 to +111 with these budgets, i.e. not a reliable test.
"""

from __future__ import annotations

import statistics

import pytest
import torch

from fedhpg.common.config import RunConfig
from fedhpg.common.runtime.cli import compose
from fedhpg.common.variants import run_variants
from fedhpg.common.worker import initial_theta
from fedhpg.server.pools.inprocess import make_in_process_pool, run_in_process

MIN_GAIN = 5.0
EPISODES = 20


def _run(server_step_size: float) -> RunConfig:
    return compose(
        [
            "seed=0",
            "rounds=40",
            "env.family=halfcheetah",
            "env.level=0",
            "env.horizon=100",
            "agents.num_agents=2",
            "agents.budget.batch_size=[16]",
            "agents.budget.local_iters=[1]",
            "agents.speeds=[1]",
            "agents.step_delays_s=[0]",
            "agents.latencies_s=[0]",
            "policy.hidden=[32,32]",
            "algo.name=fedhpg",
            "algo.optimizer=sgd",
            "algo.step_size=1.0",
            "strategy=fedadam",
            f"strategy.params.step_size={server_step_size}",
            f"eval.episodes={EPISODES}",
            "eval.every=40",
        ]
    )


def _greedy_return(run: RunConfig, theta: torch.Tensor, round_index: int) -> float:
    """Mean greedy return over every agent's ``EPISODES`` episodes."""
    pool = make_in_process_pool(run, run_variants(run))
    try:
        evals = pool.evaluate(round_index, theta, EPISODES)
    finally:
        pool.close()
    return statistics.mean(e.return_mean for e in evals.values())


def _gain(server_step_size: float) -> float:
    run = _run(server_step_size)
    before = _greedy_return(run, initial_theta(run_variants(run)[0], run), 0)
    after = _greedy_return(run, run_in_process(run), run.rounds)
    return after - before


def check_learned(gain: float) -> None:
    assert gain >= MIN_GAIN, f"greedy return rose by only {gain:.1f} (need ≥ {MIN_GAIN})"


def test_halfcheetah_greedy_return_improves() -> None:
    check_learned(_gain(1e-2))


def test_the_check_fails_without_learning() -> None:
    """Same run with server step size 1e-12: θ̃ stays put, the gain is evaluation noise, and
    the same check fails."""
    with pytest.raises(AssertionError, match="rose by only"):
        check_learned(_gain(1e-12))
