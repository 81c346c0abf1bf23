"""Server strategies: each rule against a hand-written reference, arrival order irrelevant,
robust rules robust, state that survives a checkpoint, options checked by name."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.strategy import StrategyConfig
from fedhpg.common.records.types import RoundResult, UpdateColumns, UpdateStats
from fedhpg.server.strategies import STRATEGIES, make_strategy

SHIPPED = ["fedadam", "mean", "median", "trimmed_mean", "weighted"]


def _updates(count: int = 5, size: int = 300, seed: int = 0) -> RoundResult:
    generator = torch.Generator().manual_seed(seed)
    stats = [
        UpdateStats(trajectories=10 * (k + 1), env_steps=1, compute_s=0.0, train_return=0)
        for k in range(count)
    ]
    return RoundResult(
        round=1,
        agents=list(range(count)),
        thetas=torch.randn(count, size, generator=generator).numpy(),
        stats=UpdateColumns.of(stats),
    )


def _aggregate(name: str, updates: RoundResult, **params: object) -> torch.Tensor:
    strategy = make_strategy(StrategyConfig(name=name, params=dict(params)))
    return strategy.aggregate(1, torch.zeros(updates.thetas.shape[1]), updates, {})


def _rows(updates: RoundResult) -> np.ndarray:
    return updates.thetas.astype(np.float64)


def test_every_shipped_strategy_is_registered() -> None:
    assert set(SHIPPED) <= set(STRATEGIES.names())


def test_mean_and_weighted() -> None:
    updates = _updates()
    rows = _rows(updates)
    np.testing.assert_allclose(_aggregate("mean", updates).numpy(), rows.mean(0), atol=1e-6)
    weights = np.array([10, 20, 30, 40, 50]) / 150
    np.testing.assert_allclose(_aggregate("weighted", updates).numpy(), weights @ rows, atol=1e-6)


@pytest.mark.parametrize("count", [4, 5])
def test_median_is_numpys_median(count: int) -> None:
    updates = _updates(count)
    expected = np.median(_rows(updates), axis=0)  # the mean of the middle two for even K
    np.testing.assert_allclose(_aggregate("median", updates).numpy(), expected, atol=1e-6)


@pytest.mark.parametrize(("count", "fraction", "cut"), [(10, 0.2, 2), (10, 0.29, 2), (5, 0.1, 0)])
def test_trimmed_mean_drops_the_extremes(count: int, fraction: float, cut: int) -> None:
    updates = _updates(count)
    ordered = np.sort(_rows(updates), axis=0)
    expected = ordered[cut : count - cut].mean(0)
    result = _aggregate("trimmed_mean", updates, trim_fraction=fraction)
    np.testing.assert_allclose(result.numpy(), expected, atol=1e-6)


@pytest.mark.parametrize("name", SHIPPED)
def test_arrival_order_cannot_change_a_bit(name: str) -> None:
    """Whatever order the rows arrive in, the server's concatenation puts them in agent
    order: θ̃ is the same to the bit."""
    updates = _updates(4)
    reference = _aggregate(name, updates)
    rows = [updates[k : k + 1] for k in range(len(updates))]
    for order in itertools.permutations(rows):
        arrived = RoundResult.concatenated(list(order))
        assert arrived.agents == updates.agents
        assert torch.equal(_aggregate(name, arrived), reference)


def test_robust_rules_ignore_a_minority_of_huge_updates() -> None:
    """3 of 10 send 1e6 · their update: median and a trim of 0.3 stay inside the honest
    values of every coordinate; the mean is dragged far outside."""
    updates = _updates(10)
    thetas = updates.thetas.copy()
    thetas[:3] *= 1e6
    attacked = RoundResult(round=1, agents=updates.agents, thetas=thetas, stats=updates.stats)
    honest = _rows(updates[3:])
    low, high = honest.min(0) - 1e-6, honest.max(0) + 1e-6
    for name, params in [("median", {}), ("trimmed_mean", {"trim_fraction": 0.3})]:
        result = _aggregate(name, attacked, **params).numpy()
        assert np.all((low <= result) & (result <= high)), name
    assert np.abs(_aggregate("mean", attacked).numpy()).max() > 1e4


def test_weighted_survives_counts_beyond_float32() -> None:
    """Counts are normalised in float64: 3e38 trajectories do not overflow to inf/NaN."""
    updates = _updates(3)
    huge = updates.with_stats(trajectories=[int(3e38), 1, 1])
    result = _aggregate("weighted", huge)
    assert torch.isfinite(result).all()
    torch.testing.assert_close(result, torch.from_numpy(updates.thetas[0]))


def test_fedadam_first_step_is_sign_sized_and_its_state_resumes_exactly() -> None:
    updates = _updates(4)
    config = StrategyConfig(name="fedadam", params={"step_size": 0.01})
    strategy = make_strategy(config)
    theta = torch.zeros(300)
    first = strategy.aggregate(1, theta, updates, {})
    # Adam's first step is η·m̂/(√v̂ + ε) = η·g/(|g| + ε) with g the mean update: ±η.
    mean = torch.from_numpy(updates.thetas).mean(0)
    torch.testing.assert_close(first, 0.01 * mean / (mean.abs() + 1e-8))
    assert bool(((first.abs() - 0.01).abs() < 1e-6)[mean.abs() > 1e-3].all())
    second = strategy.aggregate(2, first, updates, {})
    saved = strategy.state()
    resumed = make_strategy(config)
    resumed.restore(saved)
    assert torch.equal(
        strategy.aggregate(3, second, updates, {}), resumed.aggregate(3, second, updates, {})
    )


def test_fedadam_over_median_uses_the_inner_rule() -> None:
    updates = _updates(5)
    median = _aggregate("median", updates)
    strategy = make_strategy(
        StrategyConfig(name="fedadam", params={"step_size": 1.0, "inner": "median"})
    )
    step = strategy.aggregate(1, torch.zeros(300), updates, {})
    assert torch.equal(torch.sign(step), torch.sign(median))


@pytest.mark.parametrize(
    ("name", "params", "key", "hint"),
    [
        ("nope", {}, "strategy.name", "no strategy .nope.; known: fedadam, fedpgbr, mean, median"),
        ("trimmed_mean", {"trim_fraction": 0.5}, "strategy.params.trim_fraction", r"\[0, 0.5\)"),
        ("trimmed_mean", {"trim": 0.1}, "strategy.params.trim", "allowed: trim_fraction"),
        ("mean", {"x": 1}, "strategy.params.x", "allowed: none"),
        ("fedadam", {"step_size": "big"}, "strategy.params.step_size", "must be float"),
        ("fedadam", {"inner": "nope"}, "strategy.name", "no strategy 'nope'"),
        ("fedadam", {"inner": "trimmed_mean", "inner_params": {"trim_fraction": 2.0}},
         "strategy.params.inner.params.trim_fraction", r"\[0, 0.5\)"),
    ],
)  # fmt: skip
def test_bad_options_name_the_key(name: str, params: dict, key: str, hint: str) -> None:
    with pytest.raises(ConfigError, match=hint) as info:
        make_strategy(StrategyConfig(name=name, params=params))
    assert info.value.key == key


def test_coordinate_rules_by_columns_agree_with_the_whole_matrix() -> None:
    """median and trimmed_mean in slices of columns (budgets of one to a few columns) equal the
    rule on the whole [K, d] matrix (the median bit for bit; the trimmed mean's sums, whose
    order a reduction's kernel picks by the slice's width, to float32 rounding), and leave
    the matrix as it was; within the default budget the matrix is one slice."""
    from fedhpg.server.strategies import by_columns
    from fedhpg.server.strategies.median import coordinate_median
    from fedhpg.server.strategies.trimmed_mean import trimmed_mean

    rows = torch.randn(11, 37, generator=torch.Generator().manual_seed(5))
    kept = rows.clone()
    for budget in (1, 12 * 11 * 3, 12 * 11 * 8):
        whole = coordinate_median(rows)
        assert torch.equal(by_columns(rows, coordinate_median, budget), whole)
        whole = trimmed_mean(rows, 0.2)
        torch.testing.assert_close(
            by_columns(rows, lambda r: trimmed_mean(r, 0.2), budget), whole, rtol=0, atol=1e-6
        )
    assert torch.equal(by_columns(rows, lambda r: trimmed_mean(r, 0.2)), trimmed_mean(rows, 0.2))
    assert torch.equal(rows, kept)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
@pytest.mark.parametrize("name", ["mean", "weighted", "median", "trimmed_mean"])
def test_a_rule_on_a_cuda_device_agrees_with_the_cpu(name: str) -> None:
    updates = _updates(count=9, size=50)
    on_cpu = make_strategy(StrategyConfig(name=name)).aggregate(1, torch.zeros(50), updates, {})
    on_cuda = make_strategy(StrategyConfig(name=name, device="cuda")).aggregate(
        1, torch.zeros(50), updates, {}
    )
    assert on_cuda.device.type == "cpu"
    torch.testing.assert_close(on_cuda, on_cpu)


def test_strategy_device_is_checked() -> None:
    """strategy.device takes cpu, cuda, cuda:N (a typo is refused naming the key), and a
    server whose torch sees no such device is refused before it starts."""
    from fedhpg.common.configuration.config import validate
    from fedhpg.common.runtime.cli import compose
    from fedhpg.server.strategies import validate_strategy

    with pytest.raises(ConfigError) as info:
        validate(compose(["strategy.device=gpu"]))
    assert info.value.key == "strategy.device"
    run = compose(["strategy=median", "strategy.device=cuda:7"])
    if torch.cuda.device_count() <= 7:
        with pytest.raises(ConfigError, match="CUDA") as refused:
            validate_strategy(run)
        assert refused.value.key == "strategy.device"
