"""Structure-aware fuzzing material: Hypothesis strategies over the real message dataclasses,
with every field's type at its extremes (unicode, huge and non-finite numbers, nested maps)
and, now and then, a field of the wrong type. Messages are framed with :func:`raw_frames`, so
nothing is filtered on the sending side."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from peers import Frames, raw_frames

from fedhpg.common.records.types import EvaluationStats, UpdateColumns, UpdateStats
from fedhpg.common.wire.protocol import Error, Evaluation, Heartbeat, Hello, Update

INTS = st.integers(-(2**63), 2**64 - 1)
FLOATS = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0.0, -0.0, 1e308])
NUMBERS = INTS | FLOATS
# Long strings by repetition: drawing 5,000 characters one by one would cost more than all else.
TEXT = st.text(max_size=24) | st.tuples(st.text(min_size=1, max_size=4), st.integers(50, 1500)).map(
    lambda pair: pair[0] * pair[1]
)
PLAIN = st.recursive(
    st.none() | st.booleans() | NUMBERS | TEXT | st.binary(max_size=64),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(TEXT, children, max_size=4),
    max_leaves=8,
)
WRONG = st.none() | st.booleans() | TEXT | st.binary(max_size=8) | st.lists(NUMBERS, max_size=3)


def _stats() -> st.SearchStrategy:
    return st.builds(
        UpdateStats,
        trajectories=INTS, env_steps=INTS, compute_s=FLOATS, train_return=FLOATS,
        grad_clipped=INTS, emulated_s=FLOATS, speed=FLOATS, local_wall_s=st.none() | FLOATS,
        algorithm=st.dictionaries(TEXT, FLOATS | WRONG, max_size=40),
    )  # fmt: skip


def _evaluation_stats() -> st.SearchStrategy:
    return st.builds(
        EvaluationStats,
        return_mean=FLOATS, return_std=FLOATS, discounted_return_mean=FLOATS,
        success_rate=FLOATS, length_mean=FLOATS, episodes=INTS,
    )  # fmt: skip


def _thetas(num_params: int) -> st.SearchStrategy:
    """An answer's [rows, d] matrix, now and then of the wrong size, dtype or layout."""
    sized = st.sampled_from([0, 1, num_params - 1, num_params, num_params + 1, 4 * num_params])
    return st.one_of(
        sized.map(lambda n: np.random.default_rng(n).standard_normal((1, n)).astype(np.float32)),
        st.just(np.full((1, num_params), np.nan, dtype=np.float32)),
        st.just(np.full((1, num_params), np.inf, dtype=np.float32)),
        st.just(np.full((1, num_params), 3.4e38, dtype=np.float32)),
        st.just(np.ones((1, num_params), dtype=np.float64)),
        st.just(np.ones(num_params, dtype=np.float32)),
        st.just(np.ones((2, num_params), dtype=np.float32)),
        st.just(np.ones((1, num_params), dtype=np.int64)),
    )


def messages(num_params: int, signature: dict[str, str]) -> st.SearchStrategy:
    """(message, field overrides): a message of a type agents send, and now and then one of
    its fields replaced by a value of the wrong type. The ``round`` of updates and evaluations
    is left for the sender to set (it must not collide with a round the server has open)."""
    rounds = st.just(-1)
    agents = st.sampled_from([[0], [1], [0, 1], [7], []])
    built = st.one_of(
        st.builds(
            Update,
            round=rounds,
            agents=agents,
            thetas=_thetas(num_params),
            stats=st.lists(_stats(), min_size=1, max_size=2).map(UpdateColumns.of),
        ),
        st.builds(
            Evaluation,
            round=rounds,
            agents=agents,
            stats=st.lists(_evaluation_stats(), min_size=1, max_size=2),
        ),
        st.builds(
            Hello,
            id=TEXT,
            first=INTS,
            count=INTS,
            names_agent=st.booleans(),
            env_signature=st.just(signature) | st.dictionaries(TEXT, TEXT, max_size=10),
            variant_digest=TEXT,
            profile=st.dictionaries(TEXT, PLAIN, max_size=20),
        ),
        st.builds(Error, code=TEXT, reason=TEXT),
        st.just(Heartbeat()),
    )

    @st.composite
    def with_overrides(draw: st.DrawFn) -> tuple[object, dict]:
        message = draw(built)
        names = [f.name for f in dataclasses.fields(message) if f.name not in ("thetas", "round")]
        if names and draw(st.integers(0, 4)) == 0:
            return message, {draw(st.sampled_from(names)): draw(WRONG | PLAIN)}
        return message, {}

    return with_overrides()


def generate(count: int, num_params: int, signature: dict[str, str]) -> list[tuple[object, dict]]:
    """``count`` (message, overrides) pairs, the same ones every run (derandomized).

    Hypothesis draws a quarter of them (drawing costs ~2.5 ms an example here); each drawn
    message is also sent with one field replaced by a field of another drawn message of the
    same type, and by a wrong-typed value of the next one: 4 variants per draw."""
    drawn: list[tuple[object, dict]] = []

    @settings(
        max_examples=max(count // 4, 1), database=None, derandomize=True, deadline=None,
        phases=[Phase.generate], suppress_health_check=list(HealthCheck),
    )  # fmt: skip
    @given(messages(num_params, signature))
    def collect(item: tuple[object, dict]) -> None:
        drawn.append(item)

    collect()
    found: list[tuple[object, dict]] = []
    for i, (message, overrides) in enumerate(drawn):
        found.append((message, overrides))
        donor, donor_overrides = drawn[(i * 7 + 3) % len(drawn)]
        found.append((message, donor_overrides))
        for other, _ in drawn[i + 1 :]:
            if type(other) is type(message):
                names = [f.name for f in dataclasses.fields(other) if f.name != "round"]
                if names:
                    name = names[i % len(names)]
                    found.append((dataclasses.replace(message, **{name: getattr(other, name)}), {}))
                break
        found.append((donor, overrides) if overrides else (donor, {}))
    while len(found) < count:
        found.extend(found[: count - len(found)])
    return found[:count]


def frames_of(message: object, overrides: dict, round_index: int) -> Frames | None:
    """The frames to send (``round`` set for rounded messages); None if msgpack itself cannot
    carry a value (an int beyond 64 bits, say): nothing of that kind can reach the server."""
    if any(f.name == "round" for f in dataclasses.fields(message)):  # type: ignore[arg-type]
        overrides = {"round": round_index, **overrides}
    try:
        return raw_frames(message, **overrides)
    except (OverflowError, TypeError, ValueError, msgpack.PackException):
        return None
