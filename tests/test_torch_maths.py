"""``algo.engine=torch``: the numpy engine's policy maths in torch (common/batched/torch_maths.py),
tested on the CPU against the numpy maths; a CUDA device runs the same code."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fedhpg.common.batched import batched_group_or_none, mlp
from fedhpg.common.batched.engine import BatchedFedHPG
from fedhpg.common.batched.maths import NUMPY, DeviceUnavailable, maths_for
from fedhpg.common.batched.torch_maths import TorchMaths
from fedhpg.common.config import ConfigError
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import initial_theta
from fedhpg.server.api import resolve_config

TORCH = TorchMaths("cpu")
SHAPES = [mlp.MLPShape((4, 16, 16, 2)), mlp.MLPShape((6, 32, 3)), mlp.MLPShape((8, 5))]


def _theta(shape: mlp.MLPShape, agents: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 0.7, (agents, shape.num_params)).astype(np.float32)


@pytest.mark.parametrize("shape", SHAPES, ids=str)
def test_the_draws_and_greedy_actions_are_the_numpy_maths_ones(shape: mlp.MLPShape) -> None:
    rng = np.random.default_rng(1)
    agents, copies = 200, 50  # 10,000 draws: a 0.1 % error in the CDF flips some
    theta = _theta(shape, agents, 2)
    obs = rng.normal(0, 2, (agents, copies, shape.sizes[0])).astype(np.float32)
    uniforms = rng.random(agents * copies)
    wanted = NUMPY.act(NUMPY.unflatten(shape, theta), obs, uniforms)
    got = TORCH.act(TORCH.unflatten(shape, theta), obs, uniforms)
    assert got.dtype == np.int64 and len(set(wanted.tolist())) == shape.sizes[-1]
    assert np.array_equal(got, wanted)
    greedy = TORCH.act(TORCH.unflatten(shape, theta), obs, None)
    assert np.array_equal(greedy, NUMPY.act(NUMPY.unflatten(shape, theta), obs, None))


@pytest.mark.parametrize("shape", SHAPES, ids=str)
def test_the_score_gradient_is_the_numpy_maths_one(shape: mlp.MLPShape) -> None:
    rng = np.random.default_rng(3)
    agents = 11
    rows = rng.integers(1, 150, agents)  # some agents over several chunks
    owner = np.repeat(np.arange(agents), rows)
    obs = rng.normal(0, 1, (len(owner), shape.sizes[0])).astype(np.float32)
    actions = rng.integers(0, shape.sizes[-1], len(owner))
    coef = rng.normal(0, 1, len(owner)).astype(np.float32)
    chunks = mlp.pack_rows(owner, obs, actions, coef, agents)
    theta = _theta(shape, agents, 4)
    wanted = NUMPY.score_gradient(shape, NUMPY.unflatten(shape, theta), chunks)
    got = TORCH.score_gradient(shape, TORCH.unflatten(shape, theta), chunks)
    assert got.shape == (agents, shape.num_params) and got.dtype == np.float32
    # float32 sums of up to 150 rows, added in other orders
    np.testing.assert_allclose(got, wanted, rtol=0, atol=1e-5 * np.abs(wanted).max())


def test_select_and_assign_move_whole_agents() -> None:
    shape = SHAPES[0]
    layers = TORCH.unflatten(shape, _theta(shape, 6, 5))
    fresh_theta = _theta(shape, 2, 6)
    TORCH.assign(layers, np.array([4, 1]), TORCH.unflatten(shape, fresh_theta))
    picked = TORCH.select(layers, np.array([1, 4]))
    expected = TORCH.unflatten(shape, fresh_theta[::-1].copy())
    for (weight, bias), (want_w, want_b) in zip(picked, expected, strict=True):
        assert torch.equal(weight, want_w) and torch.equal(bias, want_b)


def _run(engine: str, *extra: str):
    return resolve_config(
        overrides=[
            "env=cartpole",
            "agents.num_agents=6",
            "agents=population",
            "policy.hidden=[16,16]",
            f"algo.engine={engine}",
            *extra,
        ]
    )


def test_the_torch_engine_trains_with_torch_and_lands_where_the_numpy_engine_does() -> None:
    """Same streams, same formulas: on the CPU the draws agree, so the episodes are the same
    and θ differs by float32 rounding alone."""
    results = {}
    start = initial_theta(variants_of(_run("numpy"), [0])[0], _run("numpy"))
    for engine in ("numpy", "torch"):
        run = _run(engine)
        group = batched_group_or_none(run, variants_of(run, range(6)))
        assert isinstance(group, BatchedFedHPG)
        assert isinstance(group.maths, TorchMaths if engine == "torch" else type(NUMPY))
        results[engine] = group.train(2, start, list(range(6)))
    for k, numpy_result in results["numpy"].items():
        torch_result = results["torch"][k]
        assert torch_result.stats.env_steps == numpy_result.stats.env_steps
        assert torch_result.stats.train_return == numpy_result.stats.train_return
        moved = float((numpy_result.theta - start).abs().max())
        assert moved > 1e-3
        assert float((torch_result.theta - numpy_result.theta).abs().max()) <= 1e-4 * moved


def test_a_device_needs_the_torch_engine_and_a_known_name() -> None:
    with pytest.raises(ConfigError, match=r"algo.device: 'cuda' needs algo.engine=torch"):
        _run("numpy", "algo.device=cuda")
    with pytest.raises(ConfigError, match=r"algo.device: got 'gpu', allowed: cpu, cuda, cuda:N"):
        _run("torch", "algo.device=gpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_a_missing_cuda_device_is_one_line_before_anything_starts(tmp_path: Path) -> None:
    with pytest.raises(DeviceUnavailable, match="torch sees no CUDA device"):
        maths_for("torch", "cuda")
    done = subprocess.run(
        [Path(sys.executable).parent / "fedhpg-run", "rounds=1", "algo.engine=torch",
         "algo.device=cuda", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: algo.device: 'cuda': torch sees no CUDA device on this machine"
    ]
