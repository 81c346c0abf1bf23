"""The update check of a host's batch: one pass over the [A, d] matrix, row by row the answer
:meth:`UpdateCheck.problem` gives for that row alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fedhpg.common.records.types import UpdateStats
from fedhpg.server.validation import (
    NON_FINITE,
    Reject,
    Rejection,
    UpdateCheck,
    diverged,
    reasons,
)

D = 64
STATS = UpdateStats(trajectories=4, env_steps=80, compute_s=0.1, train_return=20.0)


def _rows() -> np.ndarray:
    rng = np.random.default_rng(3)
    rows = (rng.standard_normal((7, D)) * 0.05).astype(np.float32)
    rows[1, 5] = np.nan
    rows[2, -1] = np.inf
    rows[3, 0] = -np.inf
    rows[4] = np.float32(3e38)  # finite, but the row's float32 sum overflows to inf
    rows[5] *= 40.0  # far from θ̃: only a norm bound refuses it
    return rows


@pytest.mark.parametrize("bound", [None, 1.0, 1e39])
@pytest.mark.parametrize("broadcast", [None, "zeros"])
def test_a_batch_gets_the_answer_of_each_row_alone(
    bound: float | None, broadcast: str | None
) -> None:
    check = UpdateCheck(num_params=D, max_update_norm=bound)
    rows = _rows()
    theta = None if broadcast is None else np.zeros(D, dtype=np.float32)
    stats = [STATS] * len(rows)
    alone = [check.problem(row, STATS, theta, stats_bounded=True) for row in rows]
    assert check.problems(rows, stats, theta, stats_bounded=True) == alone
    assert alone[1] == alone[2] == alone[3] == Rejection(Reject.NON_FINITE, NON_FINITE)
    assert alone[4] is None if bound is None or theta is None else alone[4] is not None
    assert alone[0] is None and alone[6] is None
    assert (alone[5] is not None) == (bound == 1.0 and theta is not None)
    if alone[5] is not None:
        assert alone[5].code is Reject.TOO_FAR and "server.max_update_norm" in alone[5].reason


def test_a_batch_of_the_wrong_layout_or_stats_is_refused_row_by_row() -> None:
    check = UpdateCheck(num_params=D)
    rows = _rows()
    stats = [STATS] * len(rows)
    for bad in (rows.astype(np.float64), rows[:, :-1]):
        expected = [check.problem(row, STATS, None) for row in bad]
        assert check.problems(bad, stats, None) == expected
        assert len(set(expected)) == 1 and expected[0] is not None
        assert expected[0].code is Reject.LAYOUT
    # stats are checked here unless the codec did (stats_bounded)
    negative = dataclasses.replace(STATS, env_steps=-1)
    mixed = [negative] + [STATS] * (len(rows) - 1)
    expected = [check.problem(row, s, None) for row, s in zip(rows, mixed, strict=True)]
    assert check.problems(rows, mixed, None) == expected
    assert expected[0] is not None and expected[0].code is Reject.STATS
    assert expected[0].reason.startswith("update stats: ")


def test_divergence_is_told_by_the_rejections_code_not_by_its_words() -> None:
    """The round loop stops a run as diverged when every rejected update was non-finite: the
    code says so, whatever a reason's text happens to contain; a checkpoint keeps both."""
    nan = Rejection(Reject.NON_FINITE, NON_FINITE)
    wordy = Rejection(Reject.STATS, f"update stats: {NON_FINITE} (a reason, not a code)")
    assert diverged({"agent-0": nan, "agent-1": nan})
    assert not diverged({}) and not diverged({"agent-0": nan, "agent-1": wordy})
    assert reasons({"agent-1": wordy}) == {"agent-1": wordy.reason}
    assert Rejection.restore(nan.saved()) == nan
    assert Rejection.restore("an older checkpoint's reason").code is Reject.UNKNOWN
