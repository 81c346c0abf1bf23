"""The compiled estimator (common/learning/batched/estimator.py) against its definition, the torch
estimator (common/learning/estimators.py through common/learning/engine/estimate.py) on the padded
batch: the same bits (``np.array_equal`` on float64) for every option the torch
code takes, on random staircases of rows (single trajectories, empty rows between others, a
lone row), CartPole's rewards and signed ones, per-row discounts, importance weights, and any
order of the packed steps; the same ValueErrors where it refuses; a row's numbers the same in
any company."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from fedhpg.common.learning.batched.estimator import packed_coefficients
from fedhpg.common.learning.engine.estimate import EstimatorOptions, batch_coefficients
from fedhpg.common.learning.engine.trajectories import StepRows, Trajectories

WEIGHTINGS = ("none", "trajectory", "decision")


def _accepted(estimator: str, reward_to_go: str, weighting: str) -> bool:
    """What the torch definition computes (it raises ValueError for the rest)."""
    return estimator == "gpomdp" or (reward_to_go == "from_start" and weighting != "decision")


COMBINATIONS = [
    (EstimatorOptions(estimator, baseline, reward_to_go, normalize), weighting)  # type: ignore[arg-type]
    for estimator, baseline, reward_to_go, normalize, weighting in itertools.product(
        ("reinforce", "gpomdp"),
        ("none", "mean"),
        ("from_start", "from_step"),
        ("none", "batch", "episode"),
        WEIGHTINGS,
    )
    if _accepted(estimator, reward_to_go, weighting)
]
REFUSED = [
    (EstimatorOptions("reinforce", baseline, reward_to_go, normalize), weighting)  # type: ignore[arg-type]
    for baseline, reward_to_go, normalize, weighting in itertools.product(
        ("none", "mean"), ("from_start", "from_step"), ("none", "batch", "episode"), WEIGHTINGS
    )
    if not _accepted("reinforce", reward_to_go, weighting)
]


@dataclass
class Batch:
    """A random batch, its steps packed: the arguments of :func:`packed_coefficients`."""

    rewards: np.ndarray
    time: np.ndarray
    column: np.ndarray
    lengths: np.ndarray
    owner: np.ndarray
    counts: np.ndarray
    gammas: np.ndarray
    per_trajectory: np.ndarray
    per_decision: np.ndarray

    def weights(self, weighting: str) -> np.ndarray | None:
        return {"none": None, "trajectory": self.per_trajectory, "decision": self.per_decision}[
            weighting
        ]


def _sampler_order(lengths: np.ndarray, owner: np.ndarray, rows: int) -> np.ndarray:
    """(t, n) of every step as the compiled sampler packs them: row after row, within a row
    time-major, its surviving trajectories in column order at each t."""
    steps = []
    for row in range(rows):
        columns = np.flatnonzero(owner == row)
        longest = int(lengths[columns].max()) if columns.size else 0
        steps += [(t, int(n)) for t in range(longest) for n in columns if t < lengths[n]]
    return np.array(steps, dtype=np.int64).reshape(-1, 2)


def _random_batch(rng: np.random.Generator, permute: bool = True) -> Batch:
    shape = rng.choice(["lone", "rows", "rows"])
    rows = 1 if shape == "lone" else int(rng.integers(2, 7))
    counts = rng.integers(1, 7, rows) if shape == "lone" else rng.integers(0, 7, rows)
    if rng.random() < 0.3:
        counts[rng.integers(0, rows)] = 1  # a row of a single trajectory
    if counts.sum() == 0:
        counts[-1] = 1
    owner = np.repeat(np.arange(rows), counts)
    columns = int(counts.sum())
    spread = rng.choice(["wide", "cartpole", "equal", "short"])
    if spread == "wide":
        lengths = rng.integers(1, 61, columns)
    elif spread == "cartpole":
        lengths = rng.integers(9, 40, columns)
    elif spread == "equal":  # every trajectory of a row as long as the others
        lengths = rng.integers(1, 30, rows)[owner]
    else:
        lengths = rng.integers(1, 4, columns)
    steps = _sampler_order(lengths, owner, rows)
    if permute:
        steps = steps[rng.permutation(len(steps))]
    cartpole = rng.random() < 0.4  # a reward of 1 a step
    rewards = np.ones(len(steps)) if cartpole else rng.normal(0.0, 2.0, len(steps))
    gammas = np.array([rng.choice([1.0, 0.99, float(rng.uniform(0.5, 1.0))]) for _ in range(rows)])
    longest = int(lengths.max())
    return Batch(
        rewards=rewards,
        time=steps[:, 0].copy(),
        column=steps[:, 1].copy(),
        lengths=lengths.astype(np.int64),
        owner=owner.astype(np.int64),
        counts=counts.astype(np.int64),
        gammas=gammas,
        per_trajectory=rng.lognormal(0.0, 0.5, columns),
        per_decision=rng.lognormal(0.0, 0.5, (longest + int(rng.integers(0, 3)), columns)),
    )


def _padded(batch: Batch) -> Trajectories:
    """The batch padded to its longest trajectory (the torch definition's own input)."""
    steps, columns = int(batch.lengths.max()), batch.lengths.shape[0]
    rewards = torch.zeros((steps, columns), dtype=torch.float64)
    alive = torch.zeros((steps, columns), dtype=torch.bool)
    time, column = torch.from_numpy(batch.time), torch.from_numpy(batch.column)
    rewards[time, column] = torch.from_numpy(batch.rewards)
    alive[time, column] = True
    return Trajectories(
        success=torch.zeros(columns, dtype=torch.bool),
        owner=torch.from_numpy(batch.owner),
        counts=torch.from_numpy(batch.counts),
        rewards=rewards,
        alive=alive,
        obs=torch.zeros((steps, columns, 1)),
        actions=torch.zeros((steps, columns), dtype=torch.int64),
    )


def _packed(batch: Batch) -> Trajectories:
    """The batch as the compiled backend hands it over: packed steps (the padded tensors
    built from them)."""
    packed = len(batch.time)
    per_row = np.bincount(batch.owner, weights=batch.lengths, minlength=len(batch.counts))
    steps = StepRows(
        obs=torch.zeros((packed, 1)),
        actions=torch.zeros(packed, dtype=torch.int64),
        rewards=torch.from_numpy(batch.rewards),
        time=torch.from_numpy(batch.time),
        column=torch.from_numpy(batch.column),
        rows=torch.arange(len(batch.counts)),
        row_start=torch.from_numpy(np.concatenate([[0], np.cumsum(per_row)]).astype(np.int64)),
    )
    return Trajectories(
        success=torch.zeros(len(batch.lengths), dtype=torch.bool),
        owner=torch.from_numpy(batch.owner),
        counts=torch.from_numpy(batch.counts),
        lengths=torch.from_numpy(batch.lengths),
        steps=steps,
    )


def _torch(trajectories: Trajectories, batch: Batch, options: EstimatorOptions,
           weighting: str) -> np.ndarray:  # fmt: skip
    """batch_coefficients at each packed step."""
    weights = batch.weights(weighting)
    cells = batch_coefficients(
        trajectories,
        options,
        torch.from_numpy(batch.gammas),
        None if weights is None else torch.from_numpy(weights),
    )
    time, column = torch.from_numpy(batch.time), torch.from_numpy(batch.column)
    return cells[trajectories.layout.cell(time, column)].numpy()


def _ours(batch: Batch, options: EstimatorOptions, weighting: str) -> np.ndarray:
    return packed_coefficients(
        options, batch.rewards, batch.time, batch.column, batch.lengths, batch.owner,
        batch.gammas, batch.weights(weighting),
    )  # fmt: skip


def _same_bits(ours: np.ndarray, expected: np.ndarray, label: object) -> None:
    assert ours.dtype == np.float64 and ours.shape == expected.shape, label
    if not np.array_equal(ours, expected):
        worst = np.abs(ours - expected).max()
        raise AssertionError(f"{label}: {np.sum(ours != expected)} differ, at most {worst}")


SEEDS = range(80)


def test_the_random_batches_cover_the_cases() -> None:
    """The seeds of the bit-equality test reach every kind of batch it is meant to."""
    seen: set[str] = set()
    for seed in SEEDS:
        batch = _random_batch(np.random.default_rng(seed))
        counts = batch.counts
        seen.add("lone row" if len(counts) == 1 else "several rows")
        before, after = np.cumsum(counts) - counts, counts[::-1].cumsum()[::-1] - counts
        if np.any((counts == 0) & (before > 0) & (after > 0)):
            seen.add("an empty row between others")
        seen |= {"single trajectory"} if np.any(counts == 1) else set()
        seen |= {"one-step trajectory"} if np.any(batch.lengths == 1) else set()
        seen |= {"trajectories of 50+ steps"} if np.any(batch.lengths > 50) else set()
        seen |= {"trajectories of a row of different lengths"} if any(
            np.unique(batch.lengths[batch.owner == row]).size > 1 for row in range(len(counts))
        ) else set()  # fmt: skip
        seen.add("rewards of 1" if np.all(batch.rewards == 1.0) else "signed rewards")
        seen |= {f"gamma {g}" for g in (1.0, 0.99) if np.any(batch.gammas == g)}
        seen |= {"gamma in (0.5, 1)"} if np.any(batch.gammas < 0.99) else set()
    assert seen == {
        "lone row", "several rows", "an empty row between others", "single trajectory",
        "one-step trajectory", "trajectories of 50+ steps",
        "trajectories of a row of different lengths", "rewards of 1", "signed rewards",
        "gamma 1.0", "gamma 0.99", "gamma in (0.5, 1)",
    }  # fmt: skip


@pytest.mark.parametrize("seed", SEEDS)
def test_every_option_gives_the_torch_definitions_bits(seed: int) -> None:
    rng = np.random.default_rng(seed)
    batch = _random_batch(rng)
    for options, weighting in COMBINATIONS:
        expected = _torch(_padded(batch), batch, options, weighting)
        _same_bits(_ours(batch, options, weighting), expected, (seed, options, weighting))


@pytest.mark.parametrize("seed", range(100, 120))
def test_the_packed_batchs_torch_path_agrees(seed: int) -> None:
    """The torch definition on the batch as the compiled sampler packs it (its cells placed
    from the packed steps) gives the same bits too."""
    rng = np.random.default_rng(seed)
    batch = _random_batch(rng, permute=False)
    for options, weighting in COMBINATIONS:
        expected = _torch(_packed(batch), batch, options, weighting)
        _same_bits(_ours(batch, options, weighting), expected, (seed, options, weighting))


@pytest.mark.parametrize("seed", range(200, 220))
def test_a_row_is_the_same_in_any_company(seed: int) -> None:
    rng = np.random.default_rng(seed)
    batch = _random_batch(rng)
    for options, weighting in COMBINATIONS:
        together = _ours(batch, options, weighting)
        for row in np.flatnonzero(batch.counts):
            columns = np.flatnonzero(batch.owner == row)
            steps = np.flatnonzero(np.isin(batch.column, columns))
            alone = Batch(
                rewards=batch.rewards[steps],
                time=batch.time[steps],
                column=batch.column[steps] - columns[0],
                lengths=batch.lengths[columns],
                owner=np.zeros(len(columns), dtype=np.int64),
                counts=batch.counts[row : row + 1],
                gammas=batch.gammas[row : row + 1],
                per_trajectory=batch.per_trajectory[columns],
                per_decision=batch.per_decision[:, columns],
            )
            label = (seed, row, options, weighting)
            _same_bits(_ours(alone, options, weighting), together[steps], label)


@pytest.mark.parametrize("options,weighting", REFUSED)
def test_it_refuses_what_the_torch_definition_refuses(
    options: EstimatorOptions, weighting: str
) -> None:
    batch = _random_batch(np.random.default_rng(7))
    assert batch.lengths.max() > 1  # per-decision weights of one step would pass as [N]
    with pytest.raises(ValueError):
        _torch(_padded(batch), batch, options, weighting)
    with pytest.raises(ValueError):
        _ours(batch, options, weighting)


def test_it_refuses_unknown_options_and_batches_that_are_not_one() -> None:
    batch = _random_batch(np.random.default_rng(3))
    for bad in (
        EstimatorOptions(estimator="ppo"),  # type: ignore[arg-type]
        EstimatorOptions(baseline="median"),  # type: ignore[arg-type]
        EstimatorOptions(reward_to_go="from_end"),  # type: ignore[arg-type]
        EstimatorOptions(normalize="row"),  # type: ignore[arg-type]
    ):
        with pytest.raises(ValueError):
            _ours(batch, bad, "none")
    options = EstimatorOptions()
    first_again = {
        name: np.concatenate([values[:-1], values[:1]])
        for name, values in (("time", batch.time), ("column", batch.column))
    }
    broken = {
        "a step missing": {"time": batch.time[1:], "column": batch.column[1:],
                           "rewards": batch.rewards[1:]},
        "a step twice": first_again,
        "past its end": {"time": batch.time + batch.lengths[batch.column]},
        "rows out of order": {"owner": batch.owner[::-1].copy()},
    }  # fmt: skip
    for label, change in broken.items():
        arguments = {
            "rewards": batch.rewards,
            "time": batch.time,
            "column": batch.column,
            "lengths": batch.lengths,
            "owner": batch.owner,
            "gammas": batch.gammas,
            **change,
        }
        if label == "rows out of order" and np.all(batch.owner == batch.owner[0]):
            continue
        with pytest.raises(ValueError):
            packed_coefficients(options, **arguments)
    short = batch.per_decision[: int(batch.lengths.max()) - 1]
    with pytest.raises(ValueError):
        packed_coefficients(
            options, batch.rewards, batch.time, batch.column, batch.lengths, batch.owner,
            batch.gammas, short,
        )  # fmt: skip


@pytest.mark.parametrize("rows", [0, 3])
def test_an_empty_batch_has_no_coefficients(rows: int) -> None:
    """No steps, no trajectories (the torch definition answers an empty tensor too, where it
    answers: with GPOMDP's mean baseline or a batch's standardisation, its ``groups.max()``
    of no columns raises)."""
    none = np.zeros(0, dtype=np.int64)
    for options, weighting in COMBINATIONS:
        weights = {"none": None, "trajectory": np.zeros(0), "decision": np.zeros((0, 0))}
        out = packed_coefficients(
            options, np.zeros(0), none, none, none, none, np.full(rows, 0.99),
            weights[weighting],
        )  # fmt: skip
        assert out.dtype == np.float64 and out.shape == (0,)
