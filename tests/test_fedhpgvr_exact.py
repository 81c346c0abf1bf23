"""FedHPGVR on the exact tabular MDP, through the engine: importance weights are the true
trajectory-probability ratios, the semi-stochastic gradient v is unbiased for ∇J(θ_n), and
near the snapshot it has less variance than plain GPOMDP on the same number of trajectories.

Each of DRAWS rows is one agent's independent step: μ from B_k trajectories at θ_0, then v
from b_k fresh trajectories at θ_n, every row sampled and differentiated in one call.
"""

from __future__ import annotations

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
    trajectory_log_probability,
)

from fedhpg.common.learning.algorithms.fedhpgvr import (
    FedHPGVRParams,
    importance_weights,
    semi_stochastic_gradient,
)
from fedhpg.common.learning.engine.engine import Engine

GAMMA = 0.9
DRAWS = 3000
SNAPSHOT_BATCH = 16  # B_k
MINI_BATCH = 4  # b_k


def _logits(scale: float = 0.0, seed: int = 1) -> torch.Tensor:
    logits = make_policy(seed=0).logits.detach().clone()
    return logits + scale * torch.randn(logits.shape, generator=torch.Generator().manual_seed(seed))


def _engine(estimator: str, baseline: str = "none") -> Engine:
    return mdp_engine(ExactMDPBatchEnv, HORIZON, DRAWS, gamma=GAMMA, estimator=estimator,
                      baseline=baseline)  # fmt: skip


def _v_draws(
    engine: Engine, params: FedHPGVRParams, snapshot: torch.Tensor, current: torch.Tensor
) -> torch.Tensor:
    """DRAWS independent semi-stochastic gradients v = mean_j[g_n − w g_0] + μ."""
    rows = engine.begin(7, snapshot.reshape(-1), list(range(DRAWS)))
    theta_0 = rows.theta
    theta_n = current.reshape(1, -1).repeat(DRAWS, 1)
    mu = rows.mean_gradients(
        theta_0, rows.sample(theta_0, torch.full((DRAWS,), SNAPSHOT_BATCH), iteration=0)
    )
    fresh = rows.sample(theta_n, torch.full((DRAWS,), MINI_BATCH), iteration=1)
    v, _ = semi_stochastic_gradient(rows, engine.run.algo, theta_n, theta_0, fresh, mu, params)
    return v.double()


def test_weights_are_the_exact_trajectory_probability_ratio() -> None:
    snapshot, current = _logits(), _logits(0.5)
    engine = _engine("reinforce")
    rows = engine.begin(3, current.reshape(-1), list(range(64)))
    batch = rows.sample(rows.theta, torch.full((64,), 4), iteration=0)
    theta_0 = snapshot.reshape(1, -1).repeat(64, 1)
    weights = importance_weights(
        rows, engine.run.algo, rows.theta, theta_0, batch, FedHPGVRParams(iw_mode="trajectory")
    )
    obs, actions, alive = (x.numpy() for x in (batch.obs, batch.actions, batch.alive))
    exact = np.exp(
        trajectory_log_probability(snapshot, obs, actions, alive)
        - trajectory_log_probability(current, obs, actions, alive)
    )
    np.testing.assert_allclose(weights.values.numpy(), exact, rtol=1e-5)
    assert np.ptp(exact) > 0.5, "the policies differ enough for the weights to matter"
    per_decision = importance_weights(
        rows, engine.run.algo, rows.theta, theta_0, batch, FedHPGVRParams(iw_mode="per_decision")
    )
    np.testing.assert_allclose(per_decision.final.numpy(), exact, rtol=1e-5)  # w_{0:H-1} = w(τ)
    assert per_decision.values.shape == batch.alive.shape


@pytest.mark.parametrize(
    ("estimator", "mode"), [("reinforce", "trajectory"), ("gpomdp", "per_decision")]
)
def test_v_is_unbiased_for_the_gradient_at_theta_n(estimator: str, mode: str) -> None:
    snapshot, current = _logits(), _logits(0.5)
    params = FedHPGVRParams(iw_mode=mode)  # type: ignore[arg-type]
    draws = _v_draws(_engine(estimator), params, snapshot, current)
    z = max_standard_errors(draws, exact_gradient(current, GAMMA))
    assert z < Z_LIMIT, f"{estimator}/{mode}: E[v] is {z:.2f} standard errors from ∇J(θ_n)"
    # ... and not merely close to the snapshot's gradient: the test can tell them apart.
    assert max_standard_errors(draws, exact_gradient(snapshot, GAMMA)) > Z_LIMIT


def test_near_the_snapshot_v_has_less_variance_than_plain_gpomdp() -> None:
    snapshot, current = _logits(), _logits(0.05)
    engine = _engine("gpomdp", baseline="mean")
    v = _v_draws(engine, FedHPGVRParams(iw_mode="per_decision"), snapshot, current)
    rows = engine.begin(9, current.reshape(-1), list(range(DRAWS)))
    plain = rows.mean_gradients(
        rows.theta, rows.sample(rows.theta, torch.full((DRAWS,), MINI_BATCH), iteration=0)
    ).double()
    variance_v, variance_plain = float(v.var(0).sum()), float(plain.var(0).sum())
    assert variance_v < variance_plain, (variance_v, variance_plain)
