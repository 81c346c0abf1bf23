"""FedPG-BR (algo=fedpgbr, strategy=fedpgbr): the Byzantine filter on constructed gradients, the
SCSG inner step unbiased on the exact MDP, agents and server agreeing on B_t, an in-process run
that learns with 3 of 10 agents Byzantine where plain averaging does not, and exact resume."""

from __future__ import annotations

import math
import statistics
from pathlib import Path

import numpy as np
import pytest
import torch
from engine_mdp import mdp_engine
from exact_mdp import (
    HORIZON,
    Z_LIMIT,
    ExactMDPBatchEnv,
    exact_gradient,
    make_policy,
    max_standard_errors,
)

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.learning.algorithms.fedhpgvr import FedHPGVRParams, semi_stochastic_gradient
from fedhpg.common.learning.algorithms.fedpgbr import FedPGBRParams, round_schedule
from fedhpg.common.learning.byzantine_filter import byzantine_filter, neighbour_distance
from fedhpg.server.commands import api

K, DIM, BATCH = 10, 400, 16
SIGMA = 3.0  # per-trajectory deviation: each coordinate's std is SIGMA / √DIM


def _honest(count: int, seed: int, signal: float = 1.0) -> torch.Tensor:
    """``count`` gradients of BATCH trajectories each: ∇J (norm ``signal``) + noise of
    E‖·‖² = SIGMA² / BATCH."""
    generator = torch.Generator().manual_seed(seed)
    true = torch.randn(DIM, generator=torch.Generator().manual_seed(99))
    true = signal * true / true.norm()
    noise = torch.randn(count, DIM, generator=generator) * SIGMA / math.sqrt(DIM * BATCH)
    return (true + noise).double()


def _attacked(kind: str, seed: int, signal: float = 2.0) -> torch.Tensor:
    """3 Byzantine rows (0-2) as common/learning/attacks.py makes them, then 7 honest ones."""
    honest = _honest(K, seed, signal)
    rows = honest.clone()
    rng = np.random.default_rng(seed)
    for k in range(3):
        if kind == "sign_flip":
            rows[k] = -2.5 * honest[k]
        else:  # random_noise: U(−1, 1) · 3 · (max − min) per coordinate
            spread = float(honest[k].max() - honest[k].min())
            rows[k] = honest[k] + torch.from_numpy(rng.uniform(-1, 1, DIM) * 3.0 * spread)
    return rows


@pytest.mark.parametrize("kind", ["sign_flip", "random_noise"])
@pytest.mark.parametrize("sigma", [SIGMA, None])
def test_the_filter_keeps_the_honest_and_drops_the_byzantine(
    kind: str, sigma: float | None
) -> None:
    """‖∇J‖ = 2: a sign-flipper lies ≈ 7.3 from the honest, beyond the paper's rule-1
    threshold 2σ√(V/B) ≈ 4.0, where the honest lie ≈ 1.06 apart."""
    for seed in range(5):
        found = byzantine_filter(
            _attacked(kind, seed), batch_size=BATCH, sigma=sigma, delta=0.6, alpha=0.4
        )
        assert found.kept == list(range(3, K)), (seed, found)
        assert found.rule == 1


def test_where_the_gradient_is_small_only_the_estimated_sigma_drops_sign_flippers() -> None:
    """‖∇J‖ = 0.5: −2.5× flipped gradients lie ≈ 2.5 from the honest, inside the threshold of
    the true σ (≈ 4.0) but outside the estimated one (1.5 × the ≈ 1.06 honest distance)."""
    for seed in range(5):
        rows = _attacked("sign_flip", seed, signal=0.5)
        paper = byzantine_filter(rows, batch_size=BATCH, sigma=SIGMA, delta=0.6, alpha=0.4)
        assert paper.kept == list(range(K)), (seed, paper)
        estimated = byzantine_filter(rows, batch_size=BATCH, sigma=None, delta=0.6, alpha=0.4)
        assert estimated.kept == list(range(3, K)), (seed, estimated)


def test_without_attackers_the_filter_keeps_everyone() -> None:
    for seed in range(5):
        found = byzantine_filter(
            _honest(K, seed), batch_size=BATCH, sigma=None, delta=0.6, alpha=0.4
        )
        assert found.kept == list(range(K)), (seed, found)


def test_rule_two_decides_where_rule_one_keeps_too_few() -> None:
    # σ given 4x too small: rule 1's 2σ√(V/B) ≈ 1.0 lies at the ≈ 1.06 between honest
    # gradients, so it keeps too few; rule 2's 2σ = 1.5 keeps exactly the honest ones (the
    # sign-flippers lie ≈ 7 away).
    found = byzantine_filter(
        _attacked("sign_flip", 0), batch_size=BATCH, sigma=SIGMA / 4, delta=0.6, alpha=0.4
    )
    assert found.rule == 2 and found.kept == list(range(3, K)), found
    # no majority anywhere: nothing kept, and the result says so
    spread = torch.eye(K, dtype=torch.float64) * 100
    nothing = byzantine_filter(spread, batch_size=BATCH, sigma=1.0, delta=0.6, alpha=0.4)
    assert nothing.kept == [] and nothing.rule == 0


def test_the_neighbour_distance_is_an_honest_distance_whatever_the_attackers_send() -> None:
    """Two honest gradients differ by σ√(2/B) in expectation; 3 of 10 rows moved 100x away
    leave the estimate where it was (±10%: the order statistic of 45 pairs of a 400-dim χ)."""
    expected = SIGMA * math.sqrt(2 / BATCH)
    honest = _honest(K, 1)
    moved = honest.clone()
    moved[:3] *= 100
    for rows in (honest, moved):
        assert neighbour_distance(rows) == pytest.approx(expected, rel=0.1)


def test_the_round_schedule_is_fedpgbrs_and_deterministic() -> None:
    params = FedPGBRParams(batch_min=14, batch_max=18, mini_batch_size=4)
    plans = [round_schedule(3, t, params) for t in range(1, 2001)]
    assert plans == [round_schedule(3, t, params) for t in range(1, 2001)]
    sizes = [p.batch_size for p in plans]
    assert set(sizes) == set(range(14, 19))
    # N_t ~ Geom(b/(B+b)) on {1, 2, …}: E[N_t | B_t] = (B_t + b)/b, sd √(1−p)/p ≈ 4.5 at B=16
    ratios = [p.inner_steps * 4 / (p.batch_size + 4) for p in plans]
    assert min(p.inner_steps for p in plans) >= 1
    assert statistics.mean(ratios) == pytest.approx(1.0, abs=4 * 0.95 / math.sqrt(2000))
    other_seed = [round_schedule(4, t, params) for t in range(1, 2001)]
    assert other_seed != plans


def test_the_inner_step_is_unbiased_for_the_gradient_at_theta_n() -> None:
    """v = (1/b) Σ [g(τ|θ_n) − ω g(τ|θ_0)] + μ with trajectory weights and GPOMDP (FedPG-BR's
    form, the server's inner step): with μ = ∇J(θ_0) exactly, E[v] = ∇J(θ_n) on the exact MDP
    (no baseline: a batch baseline makes each term slightly biased). One row per draw."""
    snapshot = make_policy(seed=0).logits.detach()
    current = snapshot + 0.5 * torch.randn(
        snapshot.shape, generator=torch.Generator().manual_seed(1)
    )
    gamma, b, draws = 0.9, 4, 1500
    engine = mdp_engine(ExactMDPBatchEnv, HORIZON, draws, gamma=gamma, estimator="gpomdp")
    rows = engine.begin(1, current.reshape(-1), list(range(draws)))
    theta_0 = snapshot.reshape(1, -1).repeat(draws, 1)
    mu = exact_gradient(snapshot, gamma).float().reshape(1, -1).repeat(draws, 1)
    batch = rows.sample(rows.theta, torch.full((draws,), b), iteration=0)
    v, _ = semi_stochastic_gradient(
        rows, engine.run.algo, rows.theta, theta_0, batch, mu, FedHPGVRParams(iw_mode="trajectory")
    )
    z = max_standard_errors(v.double(), exact_gradient(current, gamma).flatten())
    assert z < Z_LIMIT, f"E[v] is {z:.2f} standard errors from ∇J(θ_n)"
    assert max_standard_errors(v.double(), exact_gradient(snapshot, gamma).flatten()) > Z_LIMIT


ATTACKED_GRID = [
    "agents=homogeneous10",
    "env=gridworld",
    "env.level=0",
    "attack=sign_flip",
    "agents.step_delays_s=[0]",
    "rounds=10",
    "eval.every=5",
    # the stochastic policy's success over 10 × 50 episodes (sd ≈ 0.02): after 10 rounds the
    # greedy one is all or nothing (every agent has the same empty grid), so a seed decides it
    "eval.greedy=false",
    "eval.episodes=50",
    "seed=0",
]


def _success(result: api.RunResult) -> float:
    final = [r for r in result.records if "eval" in r][-1]["eval"]
    return statistics.mean(e["success_rate"] for e in final.values())


def test_fedpgbr_learns_under_attack_where_the_mean_does_not() -> None:
    fedpgbr = api.run(overrides=[*ATTACKED_GRID, "algo=fedpgbr", "strategy.params.step_size=0.05"])
    mean = api.run(overrides=[*ATTACKED_GRID, "algo=fedhpg", "strategy=mean"])
    assert _success(fedpgbr) >= 0.9, _success(fedpgbr)
    assert _success(mean) <= 0.5, _success(mean)
    kept = [k for r in fedpgbr.records for k in r["strategy"]["kept"]]
    rounds = len(fedpgbr.records)
    attackers = sum(k < 3 for k in kept) / (3 * rounds)
    honest = sum(k >= 3 for k in kept) / (7 * rounds)
    assert attackers <= 0.4 and honest >= 0.9, (attackers, honest)
    # agents and server drew the same B_t: every agent sampled what the filter assumed; the
    # count per agent is B_t plus the server's b·N_t shared among the K = 10
    counted = 0.0
    for record in fedpgbr.records:
        plan = record["strategy"]
        assert {a["trajectories"] for a in record["agents"]} == {plan["batch_size"]}
        assert plan["trajectories"] == 4 * plan["inner_steps"]
        counted += plan["batch_size"] + plan["trajectories"] / 10
        assert record["trajectories_per_agent"] == pytest.approx(counted)


def test_a_resumed_fedpgbr_run_matches_a_straight_one(tmp_path: Path) -> None:
    grid = [*ATTACKED_GRID, "algo=fedpgbr", "strategy.params.step_size=0.05"]
    out_dir = tmp_path / "run"
    api.run(overrides=[*grid, "rounds=2"], out_dir=out_dir)
    resumed = api.run(overrides=[*grid, "rounds=4", "resume=true"], out_dir=out_dir)
    straight = api.run(overrides=[*grid, "rounds=4"])
    assert torch.equal(resumed.theta, straight.theta)
    assert [r["strategy"] for r in resumed.records] == [r["strategy"] for r in straight.records]


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["algo=fedpgbr", "strategy=median"], "strategy"),
        (["strategy=fedpgbr"], "strategy"),
        (["algo=fedpgbr", "strategy.params.alpha=0.5"], "strategy.params.alpha"),
        (["algo=fedpgbr", "algo.params.batch_max=3"], "algo.params.batch_max"),
        (["algo=fedpgbr", "algo.estimator=reinforce"], "algo.estimator"),
        (
            ["algo=fedpgbr", "strategy.params.server_env_agent=4"],
            "strategy.params.server_env_agent",
        ),
    ],
)
def test_config_errors_name_the_key(overrides: list[str], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        api.resolve_config(overrides=overrides)
    assert info.value.key == key
    assert "\n" not in str(info.value)
