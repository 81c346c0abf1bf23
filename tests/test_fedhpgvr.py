"""FedHPGVR's semi-stochastic gradient on the engine: at the snapshot the weights are exactly 1
and v is μ; off it the weights are the trajectories' probability ratios; clipping and
self-normalisation do what they say, per agent."""

from __future__ import annotations

import ast
import inspect
from itertools import pairwise

import pytest
import torch

from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.algorithms.fedhpgvr import (
    FedHPGVRParams,
    importance_weights,
    semi_stochastic_gradient,
)
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.engine.round import Round
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.importance import self_normalise
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose


def _cartpole(estimator: str = "gpomdp") -> tuple[Engine, Round, torch.Tensor, Trajectories]:
    run = compose([
        "env=cartpole", "algo=fedhpgvr", "algo.engine=torch", f"algo.estimator={estimator}",
        "policy.hidden=[16]", "agents.num_agents=3", "agents.budget.batch_size=[8]",
        "agents.speeds=[1]", "agents.step_delays_s=[0]", "env.horizon=200",
    ])  # fmt: skip
    engine = Engine(run, variants_of(run, [0, 1, 2]))
    rows = engine.begin(1, initial_theta(engine.variants[0], run), [0, 1, 2])
    theta = rows.theta + 0.2 * torch.randn(
        rows.theta.shape, generator=torch.Generator().manual_seed(0)
    )
    batch = rows.sample(theta, torch.tensor([8, 5, 6]), iteration=1)
    return engine, rows, theta, batch


@pytest.mark.parametrize(
    ("estimator", "mode"),
    [("reinforce", "trajectory"), ("gpomdp", "per_decision"), ("gpomdp", "trajectory")],
)
def test_at_the_snapshot_weights_are_one_and_v_is_mu(estimator: str, mode: str) -> None:
    engine, rows, theta, batch = _cartpole(estimator)
    params = FedHPGVRParams(iw_mode=mode)  # type: ignore[arg-type]
    weights = importance_weights(rows, engine.run.algo, theta, theta, batch, params)
    assert torch.equal(weights.values, torch.ones_like(weights.values)), "θ_n = θ_0 ⇒ w = 1"
    assert torch.equal(weights.clipped, torch.zeros_like(weights.clipped))
    mu = torch.randn(theta.shape, generator=torch.Generator().manual_seed(1))
    v, _ = semi_stochastic_gradient(rows, engine.run.algo, theta, theta, batch, mu, params)
    # g(τ|θ_n) − 1·g(τ|θ_0) vanishes term by term when θ_n = θ_0.
    torch.testing.assert_close(v, mu, atol=1e-6, rtol=0)


def test_weights_are_each_rows_probability_ratios() -> None:
    engine, rows, theta, batch = _cartpole("reinforce")
    snapshot = theta + 0.3 * torch.randn(theta.shape, generator=torch.Generator().manual_seed(2))
    weights = importance_weights(rows, engine.run.algo, theta, snapshot, batch, FedHPGVRParams())
    log_ratio = rows.log_probs(snapshot, batch) - rows.log_probs(theta, batch)
    expected = torch.where(batch.alive, log_ratio, 0.0).sum(0).exp()
    torch.testing.assert_close(weights.values, expected)
    assert not torch.allclose(weights.values, torch.ones_like(weights.values))
    clipped = importance_weights(
        rows, engine.run.algo, theta, snapshot, batch, FedHPGVRParams(iw_clip=(0.5, 2.0))
    )
    torch.testing.assert_close(clipped.values, expected.clamp(0.5, 2.0))
    changed = (expected.clamp(0.5, 2.0) != expected).double()
    torch.testing.assert_close(clipped.clipped, batch.per_row(changed) / batch.counts.double())


def test_self_normalise_averages_to_one_within_each_agent() -> None:
    weights = torch.tensor([0.1, 1.0, 5.0, 2.0, 3.0], dtype=torch.float64)
    groups = torch.tensor([0, 0, 0, 1, 1])
    normalised = self_normalise(weights, groups)
    torch.testing.assert_close(normalised[:3].mean(), torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(normalised[3:].mean(), torch.tensor(1.0, dtype=torch.float64))
    per_step = self_normalise(torch.tensor([[1.0, 3.0], [2.0, 2.0]], dtype=torch.float64))
    torch.testing.assert_close(per_step.mean(dim=-1), torch.ones(2, dtype=torch.float64))


def test_self_normalised_correction_is_a_weighted_mean() -> None:
    _, rows, theta, batch = _cartpole("reinforce")
    weights = (
        torch.rand(batch.owner.shape, generator=torch.Generator().manual_seed(3)).double() + 0.2
    )
    scaled = rows.mean_gradients(theta, batch, self_normalise(weights, batch.owner))
    plain = rows.mean_gradients(theta, batch, weights)
    # (1/b) Σ (b w_j / Σw) g_j = Σ w_j g_j / Σ w_j = (b / Σw) · (1/b) Σ w_j g_j, per agent
    factor = batch.counts.double() / batch.per_row(weights)
    torch.testing.assert_close(scaled, plain * factor.float().unsqueeze(1), atol=1e-5, rtol=1e-4)


def _field_docstrings(cls: type) -> dict[str, str]:
    """A dataclass's fields → the docstring under each (what the API reference shows)."""
    body = ast.parse(inspect.getsource(cls)).body[0].body  # type: ignore[attr-defined]
    return {
        field.target.id: ast.literal_eval(docstring.value)
        for field, docstring in pairwise(body)
        if isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name)
        if isinstance(docstring, ast.Expr) and isinstance(docstring.value, ast.Constant)
    }


@pytest.mark.parametrize("field", ["iw_clip", "iw_self_normalize"])
def test_the_biased_options_say_so_where_the_reference_shows_them(field: str) -> None:
    """docs/configuration.md and conf/algo/fedhpgvr.yaml call both biased for ∇J."""
    assert "biased" in _field_docstrings(FedHPGVRParams)[field]
