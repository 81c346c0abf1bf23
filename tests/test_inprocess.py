"""The in-process runner: seeded runs are bit-for-bit deterministic; invalid input is named."""

from __future__ import annotations

import platform

import pytest
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.agents import AgentsConfig
from fedhpg.common.configuration.settings.algo import AlgoConfig
from fedhpg.common.configuration.settings.env import EnvConfig
from fedhpg.common.configuration.settings.policy import EvalConfig
from fedhpg.common.configuration.settings.strategy import StrategyConfig
from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.memory import pin_malloc_mmap_threshold
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord


def _cartpole_run(algo: str, seed: int = 0) -> RunConfig:
    return RunConfig(
        seed=seed,
        rounds=3,
        env=EnvConfig(family="cartpole", level=0.5),
        algo=AlgoConfig(name=algo, step_size=0.01, optimizer="adam"),
        agents=AgentsConfig(
            num_agents=3,
            budget={
                "batch_size": [4, 6, 8],
                "local_iters": [1, 2, 1],
                "inner_steps": [2],
                "mini_batch_size": [3],
            },
        ),
        eval=EvalConfig(every=3, episodes=4),
    )


@pytest.mark.parametrize("algo", ["fedhpg", "fedhpgvr"])
def test_same_seed_same_theta_bit_for_bit(algo: str) -> None:
    first = run_in_process(_cartpole_run(algo))
    second = run_in_process(_cartpole_run(algo))
    assert torch.equal(first, second)
    assert not torch.equal(first, run_in_process(_cartpole_run(algo, seed=1)))


def test_records_count_the_work() -> None:
    records: list[RoundRecord] = []
    run = _cartpole_run("fedhpg")
    run_in_process(run, on_round=[lambda record, _: records.append(record)])
    assert [r.round for r in records] == [1, 2, 3]
    trajectories = records[0].result.stats.trajectories
    assert trajectories == [4 * 1, 6 * 2, 8 * 1], "B_k × τ_k trajectories per round"
    assert all(a.env_steps >= a.trajectories for a in records[0].result.stats)
    per_round = (4 + 12 + 8) / 3
    assert [r.trajectories_per_agent for r in records] == [per_round * t for t in (1, 2, 3)]
    assert all(r.to_json()["updates"] == 3 for r in records)
    assert records[-1].eval is not None and set(records[-1].eval) == {
        "agent-0",
        "agent-1",
        "agent-2",
    }
    vr_records: list[RoundRecord] = []
    run_in_process(_cartpole_run("fedhpgvr"), on_round=[lambda r, _: vr_records.append(r)])
    assert vr_records[0].result.stats.trajectories == [4 + 2 * 3, 6 + 2 * 3, 8 + 2 * 3]
    assert {"iw_mean", "iw_max", "iw_clipped_fraction"} <= set(vr_records[0].agent_rows[0])


def test_unknown_env_family_is_named() -> None:
    run = _cartpole_run("fedhpg")
    run.env.family = "atari"
    with pytest.raises(ValueError, match="unknown environment family 'atari'; known: "):
        run_in_process(run)


def test_server_adam_takes_sign_sized_first_steps() -> None:
    """With strategy=fedadam the server treats θ̄ − θ̃ as a pseudo-gradient: Adam's
    first step moves every coordinate with a non-zero update by ≈ the server step size."""
    run = _cartpole_run("fedhpg")
    run.rounds = 1
    run.algo.optimizer = "sgd"
    run.algo.step_size = 1.0
    run.strategy = StrategyConfig(name="fedadam", params={"step_size": 0.01})
    start = initial_theta(run_variants(run)[0], run)
    moved = (run_in_process(run) - start).abs()
    assert torch.all(moved <= 0.01 + 1e-6)
    assert (moved > 0.0099).float().mean() > 0.5


@pytest.mark.parametrize("algo", ["fedhpg", "fedhpgvr"])
@pytest.mark.parametrize("estimator", ["reinforce", "gpomdp"])
def test_continuous_actions_run_through_both_algorithms(algo: str, estimator: str) -> None:
    """Pendulum (Box actions, Gaussian policy) through sampler, estimator and algorithm."""
    run = RunConfig(
        seed=0,
        rounds=2,
        env=EnvConfig(family="pendulum", level=0.5, horizon=50),
        algo=AlgoConfig(name=algo, estimator=estimator, step_size=1e-3, optimizer="adam"),
        agents=AgentsConfig(
            num_agents=2,
            budget={
                "batch_size": [4],
                "local_iters": [2],
                "inner_steps": [2],
                "mini_batch_size": [2],
            },
        ),
        eval=EvalConfig(every=2, episodes=2),
    )
    records: list[RoundRecord] = []
    theta = run_in_process(run, on_round=[lambda record, _: records.append(record)])
    start = initial_theta(run_variants(run)[0], run)
    assert torch.isfinite(theta).all() and not torch.equal(theta, start)
    assert records[-1].eval is not None
    assert all(a.env_steps == a.trajectories * 50 for a in records[0].result.stats)


@pytest.mark.parametrize(("eval_horizon", "length"), [(None, 20), (50, 50)])
def test_evaluation_horizon(eval_horizon: int | None, length: int) -> None:
    """eval.horizon caps evaluation episodes (Pendulum never ends early); default: env.horizon."""
    run = RunConfig(
        rounds=1,
        env=EnvConfig(family="pendulum", level=0.0, horizon=20),
        agents=AgentsConfig(num_agents=1, budget={"batch_size": [2], "local_iters": [1]}),
        eval=EvalConfig(every=1, episodes=2, horizon=eval_horizon),
    )
    records: list[RoundRecord] = []
    run_in_process(run, on_round=[lambda record, _: records.append(record)])
    assert records[0].result.stats.env_steps[0] == 2 * 20, "training keeps env.horizon"
    assert records[0].eval is not None
    assert records[0].eval["agent-0"].length_mean == length


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_workers_pin_the_malloc_mmap_threshold() -> None:
    """Without it, agents' heaps fragment on variable-length episodes (GBs on LunarLander)."""
    assert pin_malloc_mmap_threshold()
