"""Property-based fuzz of a secure round: one registered participant (any of the round's five)
answers each of the four exchanges with what Hypothesis draws: nothing, its honest message,
that message with any of its fields (``round``, ``agents`` and every array of ``MaskKeys``,
``KeyShares``, ``MaskedUpdate``, ``Unmasking``) replaced, mutated or of the wrong type, or raw
frames the codec refuses. The messages go through the codec both ways (tests/secure_peers.py).

Whatever it sends: the server and the five honest agents never raise; a round either sums
every honest input (exactly, where the rogue's own input is honest or left out) or fails
naming the rogue's own secret; a sum that passes its checks gives a finite step."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from peers import raw_frames
from secure_peers import HonestSide, Reply, RogueSide, secure_round, step_of
from wire_fuzz import WRONG

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy.contribution import average
from fedhpg.common.records.types import UpdateColumns
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.protocol import (
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    Message,
    Unmasking,
)
from fedhpg.server.secure_sum import sum_problem

K = 6
"""Five neighbours each, t = 3: every secret has t + 2 shares."""
NUM_PARAMS = 6
FAST_EXAMPLES = 60
SLOW_EXAMPLES = 2000
FIELDS = {
    MaskKeys: ["round", "agents", "mask_keys", "seed_commitments", "signatures"],
    KeyShares: ["round", "agents", "mask_keys", "recipients", "sealed"],
    MaskedUpdate: ["round", "agents", "masked", "stats"],
    Unmasking: ["round", "agents", "owners", "kinds", "shares"],
}
MUTATIONS = ["random", "flip", "zero", "constant", "shrink", "grow", "flat", "dtype", "other"]
DTYPES = [np.uint8, np.int64, np.uint64, np.int32, np.float32, np.float64, np.bool_]
CONSTANTS = [-(2**63), -2, -1, 0, 1, 2, 3, 4, 5, 7, 255, 2**62]


def _run() -> RunConfig:
    return compose(
        ["privacy=secagg", "agents=homogeneous10", f"agents.num_agents={K}"], report=False
    )


RUN = _run()

step_plans = st.one_of(
    st.just(("honest",)),
    st.just(("silent",)),
    st.tuples(
        st.just("mutate"),
        st.lists(
            st.tuples(st.integers(0, 4), st.sampled_from(MUTATIONS), st.integers(0, 2**32 - 1)),
            min_size=1,
            max_size=3,
        ),
    ),
    st.tuples(st.just("wrong"), st.integers(0, 4), WRONG),
)
"""What the rogue does at one exchange: answer honestly, stay silent, answer with up to three
of its message's fields (by position in :data:`FIELDS`) mutated, or with one field of the
wrong type (raw frames)."""


def _array_mutation(value: np.ndarray, how: str, rng: np.random.Generator) -> np.ndarray:
    if how == "random":
        raw = rng.integers(0, 256, value.nbytes, dtype=np.uint8)
        return raw.view(value.dtype).reshape(value.shape) if value.size else value.copy()
    if how == "flip":
        out = value.copy()
        raw = out.reshape(-1).view(np.uint8) if out.size else out
        if raw.size:
            spots = rng.integers(0, raw.size, size=rng.integers(1, 4))
            raw[spots] ^= rng.integers(1, 256, size=spots.size, dtype=np.uint8)
        return out
    if how == "zero":
        return np.zeros_like(value)
    if how == "constant":
        fill = CONSTANTS[int(rng.integers(len(CONSTANTS)))]
        return np.full(value.shape, fill).astype(value.dtype)
    if how == "shrink":
        axis = int(rng.integers(value.ndim)) if value.ndim else 0
        return np.delete(value, -1, axis=axis) if value.ndim and value.shape[axis] else value[:0]
    if how == "grow":
        if not value.ndim:
            return value.reshape(1)
        axis = int(rng.integers(value.ndim))
        pad = [(0, 0)] * value.ndim
        pad[axis] = (0, 1)
        return np.pad(value, pad)
    if how == "flat":
        return value.reshape(-1)
    if how == "dtype":
        return value.astype(DTYPES[int(rng.integers(len(DTYPES)))])
    # "other": an array of a drawn shape and dtype, unrelated to the honest one
    shape = tuple(int(d) for d in rng.integers(0, 4, size=rng.integers(1, 4)))
    dtype = DTYPES[int(rng.integers(len(DTYPES)))]
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    return rng.integers(0, 256, size, dtype=np.uint8).view(dtype).reshape(shape)


def _mutated(message: Any, field: str, how: str, seed: int, rogue: int) -> Any:
    rng = np.random.default_rng(seed)
    value = getattr(message, field)
    if field == "round":
        return message.round + int(rng.integers(-2, 3))
    if field == "agents":
        choices = [[], [rogue, rogue], [(rogue + 1) % K], [rogue, (rogue + 1) % K], [rogue + K]]
        return choices[int(rng.integers(len(choices)))]
    if field == "stats":
        rows = int(rng.integers(0, 3))
        record = value[0] if len(value) else None
        return UpdateColumns.of([record] * rows) if record is not None else value
    return _array_mutation(value, how, rng)


def _script(plans: dict[type, tuple], rogue: int):
    """The rogue's answers: each of its honest messages as the plan for its type says."""

    def script(request: Message, honest: list[Reply]) -> list[Reply]:
        out: list[Reply] = []
        for message in honest:
            plan = plans.get(type(message), ("honest",))
            if plan[0] == "silent":
                continue
            if plan[0] == "honest":
                out.append(message)
                continue
            names = FIELDS[type(message)]
            if plan[0] == "wrong":
                out.append(raw_frames(message, **{names[plan[1] % len(names)]: plan[2]}))
                continue
            changes = {}
            for position, how, seed in plan[1]:
                name = names[position % len(names)]
                changes[name] = _mutated(message, name, how, seed, rogue)
            plain = {k: v for k, v in changes.items() if k in ("round", "agents")}
            typed = {k: v for k, v in changes.items() if k not in plain}
            # raw frames: nothing of ours checks them on the way out
            out.append(raw_frames(dataclasses.replace(message, **typed), **plain))
        return out

    return script


def _check_round(rogue: int, plans: dict[type, tuple]) -> None:
    sides = {k: HonestSide(RUN, k) for k in range(K)}
    sides[rogue] = RogueSide(RUN, rogue, _script(plans, rogue))
    answers = secure_round(RUN, sides)  # raises if the server or an honest agent does
    honest = [k for k in range(K) if k != rogue]
    secure = answers.secure
    assert secure is not None
    if secure.failed is not None:  # only the rogue's own secret may be what is missing
        assert f"agent {rogue}'s" in secure.failed, secure.failed
        return
    summed = answers.result.agents
    assert set(honest) <= set(summed), (summed, answers.failures)
    assert np.isfinite(secure.total).all()
    own_input_honest = all(
        plans[kind][0] == "honest" for kind in (MaskKeys, KeyShares, MaskedUpdate)
    )
    if rogue not in summed or own_input_honest:
        mean = np.mean([step_of(k, NUM_PARAMS).astype(np.float64) for k in summed], axis=0)
        assert secure.total[-2] == pytest.approx(len(summed), abs=1e-9)
        np.testing.assert_allclose(secure.total[:-2] / len(summed), mean, rtol=0, atol=1e-9)
    step, _ = average(secure.total, None)
    if sum_problem(RUN, secure, step, weighted=False) is None:
        assert np.isfinite(step).all()
        assert torch.isfinite(torch.from_numpy(step)).all()


plans_of = st.fixed_dictionaries(
    {MaskKeys: step_plans, KeyShares: step_plans, MaskedUpdate: step_plans, Unmasking: step_plans}
)


def _fuzz(examples: int):
    @settings(
        max_examples=examples,
        database=None,
        derandomize=True,
        deadline=None,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(rogue=st.integers(0, K - 1), plans=plans_of)
    def fuzz(rogue: int, plans: dict[type, tuple]) -> None:
        _check_round(rogue, plans)

    return fuzz


def test_a_rogue_participant_can_at_most_drop_itself() -> None:
    _fuzz(FAST_EXAMPLES)()


@pytest.mark.slow
def test_a_rogue_participant_can_at_most_drop_itself_long() -> None:
    _fuzz(SLOW_EXAMPLES)()
