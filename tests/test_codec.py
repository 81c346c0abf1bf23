"""The wire codec: exact round trips of every message type, a ProtocolError with the right code
for each kind of bad input, and (property-based fuzzing) no input that makes decode fail with
anything but a ProtocolError."""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fedhpg.common.privacy.contribution import RoundPrivacy
from fedhpg.common.privacy.secagg import SEALED_BYTES
from fedhpg.common.privacy.shamir import SHARE_BYTES
from fedhpg.common.records import limits
from fedhpg.common.records.columns import Columns, columns_of
from fedhpg.common.records.types import EvaluationStats, UpdateColumns, UpdateStats
from fedhpg.common.wire import codec, protocol
from fedhpg.common.wire.codec import ProtocolError, decode, encode
from fedhpg.common.wire.protocol import (
    MAX_BATCH_ANSWERS,
    MAX_HOST_AGENTS,
    MSG_TYPE_OF,
    PAYLOAD_TYPES,
    PROTOCOL_VERSION,
    Error,
    Evaluate,
    Evaluation,
    Heartbeat,
    Hello,
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    MaskRequest,
    ShareRequest,
    Shutdown,
    Train,
    Unmasking,
    UnmaskRequest,
    Update,
    Welcome,
)

THETA = np.random.default_rng(0).standard_normal(1000).astype(np.float32)
STATS = UpdateStats(
    trajectories=10,
    env_steps=321,
    compute_s=0.5,
    train_return=-1.25,
    emulated_s=2.0,
    speed=0.25,
    local_wall_s=2.5,
    algorithm={"iw_mean": 1.0, "iw_max": 2.5},
)
EVALUATION = EvaluationStats(
    return_mean=-1.5,
    return_std=0.5,
    discounted_return_mean=-1.0,
    success_rate=1.0,
    length_mean=12.0,
    episodes=20,
)
SIGNATURE = {"observation": "Discrete(25)", "action": "Discrete(4)"}


def _update(stats: Any = STATS, *, round: int = 7, theta: np.ndarray = THETA) -> Update:
    """One agent's answer: a row of one."""
    columns = UpdateColumns.of([stats]) if isinstance(stats, UpdateStats) else stats
    return Update(round=round, agents=[0], thetas=theta[None], stats=columns)


def _hello(**fields: Any) -> Hello:
    """A lone agent's hello with ``fields`` in place (values the codec may refuse)."""
    values: dict[str, Any] = {
        "id": "a",
        "first": 0,
        "count": 1,
        "env_signature": {},
        "variant_digest": "d",
    }
    return Hello(**(values | fields))


SAMPLES = [
    Hello(
        id="agent-0",
        first=0,
        count=1,
        names_agent=True,
        env_signature=SIGNATURE,
        variant_digest="0123456789abcdef",
        profile={"budget": {"batch_size": 16}, "speed": 0.5, "pid": 4242, "raw": b"\x00\xff"},
    ),
    Hello(
        id="host-0-499",
        first=0,
        count=500,
        env_signature=SIGNATURE,
        variant_digest="0123456789abcdef",
        profile={"pid": 4242, "agents": 500},
    ),
    Welcome(
        run_id="abc",
        first=3,
        count=1,
        run={"seed": 1, "algo": {"name": "fedhpg", "lr": 0.01}, "tags": ["a", None, True]},
    ),
    Welcome(run_id="abc", first=500, count=500, run={"seed": 1}),
    Train(round=7, theta=THETA, agents=[3]),
    Train(round=7, theta=THETA, agents=[3], budgets=[{"batch_size": 12, "local_iters": 3}]),
    Train(round=7, theta=THETA, agents=[500, 503, 999]),
    Train(
        round=7,
        theta=THETA,
        agents=[500, 503],
        budgets=[{"batch_size": 2, "local_iters": 1}, {"batch_size": 64, "local_iters": 8}],
    ),
    _update(),
    Update(
        round=7,
        agents=[500, 503, 999],
        thetas=np.stack([THETA, -THETA, 2 * THETA]),
        stats=UpdateColumns.of([STATS, dataclasses.replace(STATS, trajectories=3), STATS]),
    ),
    Evaluate(round=9, theta=THETA.astype(np.float64), episodes=20, agents=[3]),
    Evaluate(round=9, theta=THETA, episodes=20, agents=list(range(500, 1000))),
    Evaluation(round=9, agents=[3], stats=[EVALUATION]),
    Evaluation(round=9, agents=[1, 2], stats=[EVALUATION, EVALUATION]),
    Heartbeat(),
    Shutdown(reason="run complete"),
    Error(code="bad_update", reason="parameters contain NaN or Inf"),
    # secure aggregation (common/privacy/secagg.py): keys, its four exchanges
    Hello(
        id="host-0-1",
        first=0,
        count=2,
        env_signature=SIGNATURE,
        variant_digest="0123456789abcdef",
        channel_keys=np.arange(64, dtype=np.uint8).reshape(2, 32),
    ),
    Train(
        round=7,
        theta=THETA,
        agents=[0, 1],
        private=RoundPrivacy(clip=1.5, noise_std=0.25, count_std=0.5, bound=100.0),
        participants=[0, 1, 4],
        channel_keys=np.ones((3, 32), dtype=np.uint8),
    ),
    MaskKeys(
        round=7,
        agents=[0, 1],
        mask_keys=np.full((2, 32), 7, dtype=np.uint8),
        seed_commitments=np.full((2, 32), 5, dtype=np.uint8),
        signatures=np.full((2, 64), 3, dtype=np.uint8),
    ),
    ShareRequest(
        round=7,
        agents=[0, 1],
        participants=[0, 1, 4],
        mask_keys=np.full((3, 32), 7, dtype=np.uint8),
        seed_commitments=np.full((3, 32), 5, dtype=np.uint8),
        signatures=np.zeros((3, 64), dtype=np.uint8),
    ),
    KeyShares(
        round=7,
        agents=[0, 1],
        mask_keys=np.full((2, 32), 7, dtype=np.uint8),
        recipients=np.array([[1, 4], [0, 4]], dtype=np.int64),
        sealed=np.full((2, 2, SEALED_BYTES), 9, dtype=np.uint8),
    ),
    MaskRequest(
        round=7,
        agents=[0],
        senders=np.array([[1, -1]], dtype=np.int64),
        mask_keys=np.zeros((1, 2, 32), dtype=np.uint8),
        sealed=np.zeros((1, 2, SEALED_BYTES), dtype=np.uint8),
    ),
    MaskedUpdate(
        round=7,
        agents=[0, 1],
        masked=np.array([[1, -2, 3], [2**62, -(2**63), 0]], dtype=np.int64),
        stats=UpdateColumns.of([STATS, STATS]),
    ),
    UnmaskRequest(round=7, agents=[0, 1], dropped=[4], included=[0, 1]),
    Unmasking(
        round=7,
        agents=[1],
        owners=np.array([[0, 4]], dtype=np.int64),
        kinds=np.array([[2, 1]], dtype=np.uint8),
        shares=np.full((1, 2, SHARE_BYTES), 3, dtype=np.uint8),
    ),
]
WIRE_DTYPES = ["float32", "float64", "int32", "int64", "uint8", "bool"]


def _same_value(a: Any, b: Any) -> bool:
    """Bit-exact equality: msgpack encodes NaN payloads, -0.0 and int-vs-float distinctly."""
    if dataclasses.is_dataclass(a):
        return _equal(a, b)
    if isinstance(a, list) and any(dataclasses.is_dataclass(item) for item in a):
        return (
            isinstance(b, list) and len(a) == len(b) and all(map(_equal, a, b))
        )  # batched answers' stats
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    return msgpack.packb(a) == msgpack.packb(b)


def _equal(a: object, b: object) -> bool:
    if type(a) is not type(b):
        return False
    return all(
        _same_value(getattr(a, f.name), getattr(b, f.name))
        for f in dataclasses.fields(a)  # type: ignore[arg-type]
    )


def _wire(message: object) -> list[bytes]:
    """What a peer receives when it copies frames out of zmq."""
    return [bytes(frame) for frame in encode(message)]  # type: ignore[arg-type]


# --- round trips ------------------------------------------------------------------------------


def test_every_message_type_has_a_sample() -> None:
    assert {type(m) for m in SAMPLES} == set(PAYLOAD_TYPES.values())


@pytest.mark.parametrize("message", SAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(message: object) -> None:
    assert _equal(decode(_wire(message)), message)
    assert _equal(decode(encode(message)), message)  # straight from encode's buffers


def test_header_layout() -> None:
    frames = encode(_update(round=3))
    assert len(frames) == 2
    assert msgpack.unpackb(frames[0]) == {
        "v": PROTOCOL_VERSION,
        "type": "update",
        "fields": {
            "round": 3,
            "agents": [0],
            "stats": {
                name: (
                    {key: [value] for key, value in STATS.algorithm.items()}
                    if name == "algorithm"
                    else [value]
                )
                for name, value in dataclasses.asdict(STATS).items()
            },
        },
        "arrays": [{"field": "thetas", "dtype": "<f4", "shape": [1, 1000]}],
    }
    assert bytes(frames[1]) == THETA.tobytes()


@pytest.mark.parametrize("dtype", WIRE_DTYPES)
@pytest.mark.parametrize("shape", [(0,), (), (3, 4), (2, 0, 3), (1_000_000,)], ids=str)
def test_arrays_round_trip_bit_exactly(dtype: str, shape: tuple[int, ...]) -> None:
    array = (np.arange(math.prod(shape)) % 7).astype(dtype).reshape(shape)
    theta = decode(_wire(Train(round=1, theta=array, agents=[0]))).theta  # type: ignore[union-attr]
    assert theta.dtype == array.dtype and theta.shape == shape
    assert theta.tobytes() == array.tobytes()


def test_float_bit_patterns_survive() -> None:
    special = np.array([np.nan, -np.nan, np.inf, -np.inf, -0.0, 1e-45, 3.4e38], dtype=np.float32)
    special = np.concatenate([special, np.array([0x7FC00001], np.uint32).view(np.float32)])
    theta = decode(_wire(Train(round=1, theta=special, agents=[0]))).theta  # type: ignore[union-attr]
    assert theta.tobytes() == special.tobytes()


def test_non_contiguous_and_big_endian_arrays_are_normalised() -> None:
    strided = np.arange(20, dtype=np.float32).reshape(4, 5)[:, ::2]
    fortran = np.asfortranarray(np.arange(12, dtype=np.int64).reshape(3, 4))
    swapped = np.arange(6, dtype=">f8").reshape(2, 3)
    for array in (strided, fortran, swapped):
        theta = decode(_wire(Train(round=1, theta=array, agents=[0]))).theta  # type: ignore[union-attr]
        np.testing.assert_array_equal(theta, array)
        assert theta.dtype.str in codec.ALLOWED_DTYPES


def test_encode_and_decode_do_not_copy_arrays() -> None:
    frames = encode(Train(round=1, theta=THETA, agents=[0]))
    assert np.shares_memory(np.frombuffer(frames[1], np.uint8), THETA)
    payload = bytearray(THETA.tobytes())  # writable, like a zmq.Frame
    theta = decode([frames[0], payload, *frames[2:]]).theta  # type: ignore[union-attr]
    assert np.shares_memory(theta, np.frombuffer(payload, np.uint8))
    assert not theta.flags.writeable  # read-only even though the frame is writable


def test_encode_normalises_numpy_scalars_and_tuples() -> None:
    stats = {"a": np.float32(0.5), "b": np.int64(3), "c": np.bool_(True), "d": (1, np.str_("x"))}
    decoded = decode(_wire(Welcome(run_id="r", first=0, count=1, run=stats)))
    assert decoded.run == {"a": 0.5, "b": 3, "c": True, "d": [1, "x"]}  # type: ignore[union-attr]
    assert type(decoded.run["b"]) is int and type(decoded.run["c"]) is bool  # type: ignore[union-attr]
    numpy_stats = dataclasses.replace(
        STATS, trajectories=np.int64(4), algorithm={"w": np.float32(0.5)}
    )
    update = decode(_wire(_update(numpy_stats, round=1)))
    assert isinstance(update, Update)
    assert update.stats[0] == dataclasses.replace(STATS, trajectories=4, algorithm={"w": 0.5})


@pytest.mark.parametrize(
    ("message", "code"),
    [
        (Train(round=1, theta=np.zeros(3, np.float16), agents=[0]), "bad_array"),
        (Train(round=1, theta=np.zeros(3, np.complex64), agents=[0]), "bad_array"),
        (Train(round=1, theta=np.array([None], dtype=object), agents=[0]), "bad_array"),
        (Train(round=1, theta=[1.0, 2.0], agents=[0]), "bad_array"),  # type: ignore[arg-type]
        (Train(round=True, theta=THETA, agents=[0]), "bad_fields"),
        (Train(round="1", theta=THETA, agents=[0]), "bad_fields"),  # type: ignore[arg-type]
        (Welcome(run_id="r", first=0, count=1, run={1: "int key"}), "bad_fields"),  # type: ignore[dict-item]
        (Welcome(run_id="r", first=0, count=1, run={"x": object()}), "bad_fields"),
        (Welcome(run_id="r", first=0, count=1, run={"x": 1 << 64}), "bad_fields"),
        (Welcome(run_id="r", first=0, count=1, run={"x": THETA}), "bad_fields"),
        (_update({"trajectories": [1]}, round=1), "bad_fields"),  # type: ignore[arg-type]
        (
            _update(dataclasses.replace(STATS, algorithm={"x": b"1"}), round=1),
            "bad_fields",
        ),  # type: ignore[dict-item]
        (
            _update(dataclasses.replace(STATS, compute_s="0"), round=1),
            "bad_fields",
        ),  # type: ignore[arg-type]
        (
            Evaluation(round=1, agents=[0], stats=[dataclasses.replace(EVALUATION, episodes=1.5)]),
            "bad_fields",
        ),  # type: ignore[arg-type]
        (_hello(env_signature={"obs": 3}), "bad_fields"),
        (Welcome(run_id="r", first=0, count=1, run={"x": "x" * (2 << 20)}), "too_large"),
        (_hello(profile={f"k{i}": "x" * 8000 for i in range(9)}), "too_large"),  # > 64 KiB
        (Shutdown(reason="x" * 5000), "bad_fields"),
        (_hello(id="a" * 129), "bad_fields"),
        (_hello(first=-1), "bad_fields"),
        (_hello(profile={f"k{i}": i for i in range(17)}), "bad_fields"),
        (_hello(names_agent=1), "bad_fields"),
        (Train(round=-1, theta=THETA, agents=[0]), "bad_fields"),
        # ranges and answers are bounded
        (_hello(count=0), "bad_fields"),
        (_hello(count=MAX_HOST_AGENTS + 1), "bad_fields"),
        (Train(round=1, theta=THETA, agents=[0] * (MAX_HOST_AGENTS + 1)), "bad_fields"),
        (Train(round=1, theta=THETA, agents=[-1]), "bad_fields"),
        (Evaluate(round=1, theta=THETA, episodes=1, agents=[-1]), "bad_fields"),
        (
            Update(
                round=1,
                agents=[0] * (MAX_BATCH_ANSWERS + 1),
                thetas=np.zeros((MAX_BATCH_ANSWERS + 1, 2), np.float32),
                stats=UpdateColumns.of([STATS] * (MAX_BATCH_ANSWERS + 1)),
            ),
            "bad_fields",
        ),
        (
            Evaluation(
                round=1,
                agents=[0] * (MAX_BATCH_ANSWERS + 1),
                stats=[EVALUATION] * (MAX_BATCH_ANSWERS + 1),
            ),
            "bad_fields",
        ),
        (
            Update(
                round=1,
                agents=[0],
                thetas=np.zeros((1, 2), np.float32),
                stats=UpdateColumns.of([dataclasses.replace(STATS, compute_s=-1.0)]),
            ),
            "bad_fields",
        ),
        (
            _update(dataclasses.replace(STATS, trajectories=limits.MAX_COUNT + 1), round=1),
            "bad_fields",
        ),
        (
            _update(dataclasses.replace(STATS, compute_s=math.inf), round=1),
            "bad_fields",
        ),
        (
            _update(dataclasses.replace(STATS, algorithm={"w": math.nan}), round=1),
            "bad_fields",
        ),
        (
            _update(
                dataclasses.replace(STATS, algorithm={f"s{i}": 1.0 for i in range(33)}), round=1
            ),
            "bad_fields",
        ),
        (
            Evaluation(
                round=1, agents=[0], stats=[dataclasses.replace(EVALUATION, success_rate=1.5)]
            ),
            "bad_fields",
        ),
    ],
    ids=lambda v: v if isinstance(v, str) else type(v).__name__,
)
def test_encode_refuses_what_decode_would_reject(message: object, code: str) -> None:
    with pytest.raises(ProtocolError) as info:
        encode(message)  # type: ignore[arg-type]
    assert info.value.code == code, str(info.value)


def test_encode_refuses_deep_nesting_and_non_messages() -> None:
    with pytest.raises(ProtocolError, match="deeper"):
        encode(Welcome(run_id="r", first=0, count=1, run={"deep": _nested(codec.MAX_NESTING + 2)}))
    with pytest.raises(TypeError):
        encode("hello")  # type: ignore[arg-type]


# --- property-based round trips ---------------------------------------------------------------

_KEYS = st.text(max_size=8)
_PLAIN = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.binary(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(_KEYS, children, max_size=4),
    max_leaves=12,
)
_STATS = st.dictionaries(_KEYS, _PLAIN, max_size=6)
# Within the fields' bounds (common/records/limits.py), extremes included.
_COUNTS = st.integers(0, limits.MAX_COUNT)
_FINITE = st.floats(allow_nan=False, allow_infinity=False)
_SECONDS = st.floats(0.0, limits.MAX_SECONDS)
_UPDATE_STATS = st.builds(
    UpdateStats,
    trajectories=_COUNTS,
    env_steps=_COUNTS,
    compute_s=_SECONDS,
    train_return=_FINITE,
    grad_clipped=_COUNTS,
    emulated_s=_SECONDS,
    speed=st.floats(0.0, 1e9),
    local_wall_s=st.none() | _SECONDS,
    algorithm=st.dictionaries(st.text(max_size=64), _FINITE, max_size=32),
)
# A batch's agents report statistics out of one set (an algorithm's), each agent a subset.
_UPDATE_COLUMNS = (
    st.lists(st.text(max_size=64), max_size=32, unique=True)
    .flatmap(
        lambda keys: st.lists(
            st.builds(
                dataclasses.replace,
                _UPDATE_STATS,
                algorithm=st.fixed_dictionaries({}, optional=dict.fromkeys(keys, _FINITE)),
            ),
            max_size=4,
        )
    )
    .map(UpdateColumns.of)
)
_EVALUATION_STATS = st.builds(
    EvaluationStats,
    return_mean=_FINITE,
    return_std=_FINITE,
    discounted_return_mean=_FINITE,
    success_rate=st.floats(0.0, 1.0),
    length_mean=st.floats(0.0, limits.MAX_COUNT),
    episodes=st.integers(1, limits.MAX_COUNT),
)
_ARRAYS = hnp.arrays(
    dtype=st.sampled_from(WIRE_DTYPES),
    shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=6),
    elements=None,
)
_ROUNDS = st.integers(0, limits.MAX_ROUND)
_AGENTS = st.lists(_ROUNDS, max_size=20)
_MESSAGES = st.one_of(
    st.builds(Train, round=_ROUNDS, theta=_ARRAYS, agents=_AGENTS),
    st.builds(
        Evaluate, round=_ROUNDS, theta=_ARRAYS, episodes=st.integers(1, 2**20), agents=_AGENTS
    ),
    st.builds(
        Hello,
        id=st.text(max_size=128),
        first=_ROUNDS,
        count=st.integers(1, MAX_HOST_AGENTS),
        names_agent=st.booleans(),
        env_signature=st.dictionaries(st.text(max_size=64), st.text(max_size=20), max_size=8),
        variant_digest=st.text(max_size=128),
        profile=st.dictionaries(st.text(max_size=64), _PLAIN, max_size=16),
    ),
    st.builds(
        Welcome,
        run_id=st.text(max_size=128),
        first=_ROUNDS,
        count=st.integers(1, MAX_HOST_AGENTS),
        run=_STATS,
    ),
    st.builds(Error, code=st.text(max_size=128), reason=st.text(max_size=4096)),
    st.builds(Shutdown, reason=st.text(max_size=200), complete=st.booleans()),
    st.builds(
        Update,
        round=_ROUNDS,
        agents=st.lists(_ROUNDS, max_size=4),
        thetas=_ARRAYS,
        stats=_UPDATE_COLUMNS,
    ),
    st.builds(
        Evaluation,
        round=_ROUNDS,
        agents=st.lists(_ROUNDS, max_size=4),
        stats=st.lists(_EVALUATION_STATS, max_size=4),
    ),
)


@settings(max_examples=400, deadline=None, derandomize=True)
@given(_MESSAGES)
def test_random_messages_round_trip(message: object) -> None:
    assert _equal(decode(_wire(message)), message)


# --- rejections -------------------------------------------------------------------------------


def _header(**overrides: object) -> bytes:
    header: dict[str, object] = {
        "v": PROTOCOL_VERSION,
        "type": "evaluate",
        "fields": _fields(),
        "arrays": [{"field": "theta", "dtype": "<f4", "shape": [2]}],
    }
    header.update(overrides)
    return msgpack.packb({k: v for k, v in header.items() if v is not _DROP})


def _fields(**overrides: object) -> dict[str, object]:
    """An Evaluate's header fields (one array, θ), with ``overrides``."""
    return {"round": 1, "episodes": 1, "agents": [0]} | overrides


def _descriptor(**overrides: object) -> bytes:
    descriptor = {"field": "theta", "dtype": "<f4", "shape": [2]} | overrides
    return _header(arrays=[descriptor])


def _packed(kind: str, **fields: object) -> bytes:
    """A header for an array-less message type."""
    return msgpack.packb({"v": PROTOCOL_VERSION, "type": kind, "fields": fields, "arrays": []})


def _nested(depth: int) -> list[Any]:
    value: list[Any] = []
    for _ in range(depth):
        value = [value]
    return value


_DROP = object()
GOOD_ARRAY = np.zeros(2, dtype=np.float32).tobytes()
REJECTIONS: list[tuple[str, list[Any], str]] = [
    # framing and msgpack
    ("no frames", [], "malformed"),
    ("not a sequence", 5, "malformed"),  # type: ignore[list-item]
    ("single buffer", b"\x80", "malformed"),  # type: ignore[list-item]
    ("frame is a str", ["header"], "malformed"),
    ("frame is an int", [7], "malformed"),
    ("strided frame", [memoryview(msgpack.packb({"v": 1}) * 2)[::2]], "malformed"),
    ("non-contiguous frame", [np.zeros((4, 4), np.uint8)[:, ::2]], "malformed"),
    ("not msgpack", [b"\xc1"], "malformed"),
    ("truncated msgpack", [b"\x82\xa1v"], "malformed"),
    ("trailing bytes", [msgpack.packb({"v": 1}) + b"\x00"], "malformed"),
    ("not a map", [msgpack.packb([1, 2])], "malformed"),
    ("int map key", [msgpack.packb({1: 2})], "malformed"),
    ("ext type", [msgpack.packb(msgpack.ExtType(1, b"x"))], "malformed"),
    ("timestamp ext", [msgpack.packb({"v": msgpack.Timestamp(1, 0)})], "malformed"),
    ("too deep", [b"\x91" * 5000 + b"\xc0"], "malformed"),
    # envelope
    ("no version", [_header(v=_DROP), GOOD_ARRAY], "malformed"),
    ("version 9", [_header(v=9), GOOD_ARRAY], "version"),
    ("version 7", [_header(v=7), GOOD_ARRAY], "version"),
    ("version 6", [_header(v=6), GOOD_ARRAY], "version"),
    ("version 5", [_header(v=5), GOOD_ARRAY], "version"),
    ("version 4", [_header(v=4), GOOD_ARRAY], "version"),
    ("version 3", [_header(v=3), GOOD_ARRAY], "version"),
    ("version 2", [_header(v=2), GOOD_ARRAY], "version"),
    ("version 1", [_header(v=1), GOOD_ARRAY], "version"),
    ("version 0", [_header(v=0), GOOD_ARRAY], "version"),
    ("version True", [_header(v=True), GOOD_ARRAY], "version"),
    ("version 3.0", [_header(v=3.0), GOOD_ARRAY], "version"),
    ("version '3'", [_header(v="3"), GOOD_ARRAY], "version"),
    ("missing key", [_header(arrays=_DROP), GOOD_ARRAY], "malformed"),
    ("extra key", [_header(extra=1), GOOD_ARRAY], "malformed"),
    ("unknown type", [_header(type="nope"), GOOD_ARRAY], "unknown_type"),
    ("type is upper case", [_header(type="EVALUATE"), GOOD_ARRAY], "unknown_type"),
    ("type not str", [_header(type=["evaluate"]), GOOD_ARRAY], "unknown_type"),
    ("fields not map", [_header(fields=[1]), GOOD_ARRAY], "malformed"),
    ("arrays not list", [_header(arrays={}), GOOD_ARRAY], "malformed"),
    # header fields
    ("missing field", [_header(fields={}), GOOD_ARRAY], "bad_fields"),
    ("unknown field", [_header(fields=_fields(extra=2)), GOOD_ARRAY], "bad_fields"),
    (
        "bytes field key",
        [_header(fields={b"round": 1, "episodes": 1, "agents": [0]}), GOOD_ARRAY],
        "bad_fields",
    ),
    ("str for int", [_header(fields=_fields(round="1")), GOOD_ARRAY], "bad_fields"),
    ("bool for int", [_header(fields=_fields(round=True)), GOOD_ARRAY], "bad_fields"),
    ("float for int", [_header(fields=_fields(round=1.0)), GOOD_ARRAY], "bad_fields"),
    ("None for int", [_header(fields=_fields(round=None)), GOOD_ARRAY], "bad_fields"),
    ("str for agent", [_header(fields=_fields(agents=["0"])), GOOD_ARRAY], "bad_fields"),
    (
        "int in dict[str, str]",
        [
            _packed(
                "hello",
                id="a",
                first=0,
                count=1,
                names_agent=True,
                env_signature={"obs": 3},
                variant_digest="d",
                profile={},
            )
        ],
        "bad_fields",
    ),
    ("stats not a list", [_packed("evaluation", round=1, agents=[0], stats={})], "bad_fields"),
    (
        "stats too deep",
        [_packed("evaluation", round=1, agents=[0], stats=[{"x": _nested(40)}])],
        "bad_fields",
    ),
    # arrays
    ("no array frame", [_header()], "bad_array"),
    ("extra frame", [_header(), GOOD_ARRAY, GOOD_ARRAY], "bad_array"),
    ("no descriptor", [_header(arrays=[]), GOOD_ARRAY], "bad_array"),
    ("descriptor not map", [_header(arrays=[["theta"]]), GOOD_ARRAY], "bad_array"),
    ("descriptor extra key", [_descriptor(order="F"), GOOD_ARRAY], "bad_array"),
    ("wrong field name", [_descriptor(field="other"), GOOD_ARRAY], "bad_array"),
    ("object dtype", [_descriptor(dtype="|O"), GOOD_ARRAY], "bad_array"),
    ("big-endian dtype", [_descriptor(dtype=">f4"), GOOD_ARRAY], "bad_array"),
    ("float16 dtype", [_descriptor(dtype="<f2", shape=[4]), GOOD_ARRAY], "bad_array"),
    ("dtype not str", [_descriptor(dtype=4), GOOD_ARRAY], "bad_array"),
    ("negative dim", [_descriptor(shape=[-2]), GOOD_ARRAY], "bad_array"),
    ("bool dim", [_descriptor(shape=[True, 2]), GOOD_ARRAY], "bad_array"),
    ("float dim", [_descriptor(shape=[2.0]), GOOD_ARRAY], "bad_array"),
    ("shape not list", [_descriptor(shape=2), GOOD_ARRAY], "bad_array"),
    ("too many dims", [_descriptor(shape=[1] * 40), GOOD_ARRAY], "bad_array"),
    ("unaddressable", [_descriptor(shape=[0, 2**47, 2**47]), b""], "bad_array"),
    ("too few bytes", [_descriptor(shape=[3]), GOOD_ARRAY], "bad_array"),
    ("too many bytes", [_header(), GOOD_ARRAY + b"\x00"], "bad_array"),
    ("bool not 0/1", [_descriptor(dtype="|b1", shape=[3]), b"\x00\x01\x02"], "bad_array"),
    ("too many frames", [_header(), *[b""] * 100], "bad_array"),
    # sizes
    ("header too large", [b"\x00" * (codec.MAX_HEADER_BYTES + 1)], "too_large"),
]


@pytest.mark.parametrize(
    ("frames", "code"), [r[1:] for r in REJECTIONS], ids=[r[0] for r in REJECTIONS]
)
def test_rejections_carry_a_code(frames: list[Any], code: str) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(frames)
    assert info.value.code == code, str(info.value)
    assert info.value.__cause__ is None, "rejected only by the safety net"
    assert len(str(info.value)) < 400  # peer data is quoted shortened


def test_version_error_names_both_versions() -> None:
    with pytest.raises(
        ProtocolError, match=rf"received protocol version 3, expected {PROTOCOL_VERSION}"
    ):
        decode([_header(v=3), GOOD_ARRAY])


def test_a_batched_answers_header_is_capped_by_the_agents_it_lists(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each row may cost what its agent's own message could (``HEADER_PER_AGENT``), no
    more: a batch cannot buy a big header with few agents. (With the real allowance no
    bounded stats reach it; a small one shows the cap is applied both ways.)"""
    lean = UpdateColumns.of([dataclasses.replace(STATS, algorithm={})] * 2)
    heavy = UpdateColumns.of(
        [dataclasses.replace(STATS, algorithm={f"{i:064d}": 1.0 for i in range(32)})] * 2
    )
    thetas = np.zeros((2, 3), np.float32)
    heavy_frames = _wire(Update(round=1, agents=[0, 1], thetas=thetas, stats=heavy))
    monkeypatch.setitem(protocol.HEADER_PER_AGENT, Update, ("agents", 256, 512))
    decode(_wire(Update(round=1, agents=[0, 1], thetas=thetas, stats=lean)))
    with pytest.raises(ProtocolError) as info:
        decode(heavy_frames)
    assert info.value.code == "too_large" and "for 2 agents" in str(info.value)
    with pytest.raises(ProtocolError, match="for 2 agents"):
        encode(Update(round=1, agents=[0, 1], thetas=thetas, stats=heavy))


def test_size_cap() -> None:
    frames = _wire(Train(round=1, theta=np.zeros(1000, dtype=np.float32), agents=[0]))
    decode(frames, max_bytes=4000 + len(frames[0]))
    with pytest.raises(ProtocolError) as info:
        decode(frames, max_bytes=4000)
    assert info.value.code == "too_large"


# --- the generic checker, on a payload class with every supported annotation ------------------


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class Probe:
    ratio: float
    maybe: int | None
    flag: bool
    items: list[int]
    nested: dict[str, list[float]]
    blob: bytes
    grid: np.ndarray
    mask: np.ndarray


@pytest.fixture
def probe_type(monkeypatch: pytest.MonkeyPatch) -> Iterator[type]:
    monkeypatch.setitem(PAYLOAD_TYPES, "probe", Probe)  # type: ignore[index]
    monkeypatch.setitem(MSG_TYPE_OF, Probe, "probe")  # type: ignore[arg-type]
    yield Probe


def _probe(**overrides: Any) -> Probe:
    values = {
        "ratio": 0.5,
        "maybe": None,
        "flag": False,
        "items": [1, 2],
        "nested": {"a": [1.5, 2]},
        "blob": b"\x00",
        "grid": np.ones((2, 2), np.float64),
        "mask": np.array([True, False]),
    }
    return Probe(**(values | overrides))


def _probe_header(**fields: Any) -> list[bytes]:
    frames = _wire(_probe())
    header = msgpack.unpackb(frames[0])
    header["fields"].update(fields)
    return [msgpack.packb(header), *frames[1:]]


def test_probe_round_trips_two_arrays(probe_type: type) -> None:
    for message in (_probe(), _probe(ratio=2, maybe=5, items=[], nested={})):
        assert _equal(decode(_wire(message)), message)


@pytest.mark.parametrize(
    "fields",
    [{"ratio": 3}, {"maybe": 7}, {"maybe": None}, {"nested": {"a": [1, 2.5]}}, {"items": []}],
    ids=str,
)
def test_probe_accepts(probe_type: type, fields: dict[str, Any]) -> None:
    decoded = decode(_probe_header(**fields))
    assert all(getattr(decoded, k) == v for k, v in fields.items())


@pytest.mark.parametrize(
    "fields",
    [
        {"ratio": True},
        {"ratio": "0.5"},
        {"ratio": None},
        {"maybe": 1.5},
        {"maybe": False},
        {"flag": 0},
        {"items": [1, "2"]},
        {"items": [True]},
        {"items": {}},
        {"nested": {"a": [None]}},
        {"nested": {"a": 1.0}},
        {"blob": "text"},
    ],
    ids=str,
)
def test_probe_rejects(probe_type: type, fields: dict[str, Any]) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(_probe_header(**fields))
    assert info.value.code == "bad_fields"
    assert next(iter(fields)) in str(info.value)  # the reason names the field


def test_probe_array_order_is_checked(probe_type: type) -> None:
    frames = _wire(_probe())
    header = msgpack.unpackb(frames[0])
    header["arrays"].reverse()
    with pytest.raises(ProtocolError) as info:
        decode([msgpack.packb(header), frames[2], frames[1]])
    assert info.value.code == "bad_array"


def test_unsupported_annotations_are_refused_up_front() -> None:
    @dataclasses.dataclass(frozen=True)
    class Odd:
        pair: tuple[int, int]

    with pytest.raises(TypeError, match="cannot go on the wire"):
        codec._specs(Odd)


# --- fuzzing ----------------------------------------------------------------------------------

_VALID = [_wire(m) for m in SAMPLES]
_ANY_MSGPACK = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=8)
    | st.sampled_from(["train", "update", "theta", "<f4", "|b1", 1, 0, -1, [], {}]),
    lambda children: (
        st.lists(children, max_size=3)
        | st.dictionaries(st.text(max_size=5) | st.binary(max_size=3), children, max_size=3)
    ),
    max_leaves=6,
)


def _replace_somewhere(draw: st.DrawFn, node: Any, depth: int = 0) -> Any:
    """``node`` with one value, at a random depth, replaced by random msgpack."""
    if isinstance(node, dict):
        children = list(node.items())
    elif isinstance(node, list):
        children = list(enumerate(node))
    else:
        children = []
    if children and (depth == 0 or draw(st.booleans())):
        key, child = draw(st.sampled_from(children))
        node[key] = _replace_somewhere(draw, child, depth + 1)
        return node
    return draw(_ANY_MSGPACK)


@st.composite
def mutated(draw: st.DrawFn) -> list[bytes]:
    frames = list(draw(st.sampled_from(_VALID)))
    kind = draw(st.sampled_from(["flip", "truncate", "drop", "extra", "swap", "header"]))
    index = draw(st.integers(0, len(frames) - 1))
    if kind == "flip" and frames[index]:
        data = bytearray(frames[index])
        for _ in range(draw(st.integers(1, 3))):
            data[draw(st.integers(0, len(data) - 1))] ^= draw(st.integers(1, 255))
        frames[index] = bytes(data)
    elif kind == "truncate":
        frames[index] = frames[index][: draw(st.integers(0, max(len(frames[index]) - 1, 0)))]
    elif kind == "drop":
        del frames[index]
    elif kind == "extra":
        frames.insert(draw(st.integers(0, len(frames))), draw(st.binary(max_size=64)))
    elif kind == "swap":
        frames.reverse()
    else:
        header = _replace_somewhere(draw, msgpack.unpackb(frames[0]))
        frames[0] = msgpack.packb(header)
    return frames


def _decode_or_reject(frames: list[bytes]) -> None:
    """Either a valid message (which then survives encode and decode again) or a
    ProtocolError raised by a rule rather than by the safety net."""
    try:
        message = decode(frames)
    except ProtocolError as error:
        assert error.__cause__ is None, f"unanticipated {error.__cause__!r}"
        return
    assert _equal(decode(_wire(message)), message)


@settings(
    max_examples=2000,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(mutated())
def test_fuzz_mutated_encodings(frames: list[bytes]) -> None:
    _decode_or_reject(frames)


@settings(max_examples=1000, deadline=None, derandomize=True)
@given(
    st.lists(
        st.binary(max_size=128) | _ANY_MSGPACK.map(lambda v: msgpack.packb(v)),
        max_size=4,
    )
)
def test_fuzz_random_frames(frames: list[bytes]) -> None:
    _decode_or_reject(frames)


# --- over real sockets ------------------------------------------------------------------------


@pytest.fixture
def router_dealer() -> Iterator[tuple[zmq.Socket, zmq.Socket]]:
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    dealer = context.socket(zmq.DEALER)
    try:
        for sock in (router, dealer):
            sock.setsockopt(zmq.LINGER, 0)
        port = router.bind_to_random_port("tcp://127.0.0.1")
        dealer.setsockopt(zmq.IDENTITY, b"agent-0#1")
        dealer.connect(f"tcp://127.0.0.1:{port}")
        yield router, dealer
    finally:
        router.close(linger=0)
        dealer.close(linger=0)
        context.term()


def test_over_real_sockets(router_dealer: tuple[zmq.Socket, zmq.Socket]) -> None:
    router, dealer = router_dealer
    big = _update(round=1, theta=np.arange(1_000_000, dtype=np.float32))
    for message in (SAMPLES[5], big):
        dealer.send_multipart(encode(message), copy=False)
        assert router.poll(5000)
        identity, *frames = router.recv_multipart(copy=False)
        assert identity.bytes == b"agent-0#1"
        assert _equal(decode(frames), message)
    router.send_multipart([b"agent-0#1", *encode(SAMPLES[4])], copy=False)
    assert dealer.poll(5000)
    assert _equal(decode(dealer.recv_multipart(copy=False)), SAMPLES[4])


def test_zmq_frames_are_accepted_directly() -> None:
    frames = [zmq.Frame(bytes(f)) for f in encode(SAMPLES[4])]
    assert _equal(decode(frames), SAMPLES[4])


_ANY_SCALAR = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=3),
)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.sampled_from([UpdateStats, EvaluationStats]), st.data())
def test_the_records_fast_path_accepts_exactly_what_the_generic_checks_do(
    record: type, data: st.DataObject
) -> None:
    """A stats record's bounded numbers are tested inline (``codec._fits``); for every field
    and any scalar, that test agrees with the field's generic check."""
    for spec in codec._specs(record):
        rule = codec._number_rule(spec.hint)
        if rule is None:
            continue
        value = data.draw(_ANY_SCALAR)
        try:
            codec._checker(spec.hint)(value, spec.name, 1)
            accepted = True
        except ProtocolError:
            accepted = False
        assert codec._fits(value, rule) == accepted, (spec.name, value)


def _outcome(check: Any, value: Any) -> tuple[bool, str]:
    try:
        check(value, "x", 1)
    except ProtocolError as error:
        return False, str(error)
    return True, ""


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    st.lists(_ANY_SCALAR, max_size=6),
    st.dictionaries(st.one_of(st.text(max_size=3), st.integers(0, 3)), _ANY_SCALAR, max_size=4),
)
def test_lists_and_maps_of_bounded_numbers_fast_path_agrees_with_the_generic_checks(
    items: list[Any], entries: dict[Any, Any]
) -> None:
    """A batch's agent indices and an update's algorithm stats are tested inline
    (``codec._check_number_list`` / ``_check_number_dict``): the same values pass, and a
    value that does not gets the generic checks' reason."""
    agents = list[limits.AgentIndex]
    algorithm = dict[str, limits.Finite]
    assert _outcome(codec._checker(agents), items) == _outcome(
        lambda v, w, d: codec._check_list(limits.AgentIndex, v, w, d), items
    )
    assert _outcome(codec._checker(algorithm), entries) == _outcome(
        lambda v, w, d: codec._check_dict(limits.Finite, v, w, d), entries
    )


_COLUMN_ITEMS = [spec.hint for spec in codec._specs(UpdateColumns) if spec.name != "algorithm"] + [
    limits.Finite | None
]
# Random mixes rarely reach the whole-list test; lists of one kind do (ints at the 64-bit edges,
# floats with ±Inf and NaN, huge ones).
_COLUMNS_OF_ONE_KIND = st.one_of(
    st.lists(_ANY_SCALAR, max_size=6),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=6),
    st.lists(st.floats(-1e10, 1e10), max_size=6),
    st.lists(st.integers(-(2**64), 2**64), max_size=6),
    st.lists(st.integers(-3, 2**41), max_size=6),
)


@settings(max_examples=400, deadline=None, derandomize=True)
@given(st.sampled_from(_COLUMN_ITEMS), _COLUMNS_OF_ONE_KIND)
@example(limits.Finite, [1, 2**70])  # beyond msgpack's ints, where no bound stops it
@example(limits.Finite, [-(2**63) - 1])
@example(limits.Finite, [2**64 - 1])
@example(limits.Seconds, [0.5, math.nan])
@example(limits.Seconds, [0.5, math.inf])
@example(limits.Count, [3, True])
@example(limits.Finite, [1.5, 2])
def test_a_columns_whole_list_test_agrees_with_the_generic_checks(
    column: Any, items: list[Any]
) -> None:
    """Every ``UpdateColumns`` column is tested as a whole (``codec._all_fit``): the same lists
    pass as item by item, and one that does not gets the generic checks' reason."""
    (item,) = (
        typing.get_args(codec.bounds_of(column)[0])
        if typing.get_origin(codec.bounds_of(column)[0]) is list
        else (column,)
    )
    assert _outcome(codec._checker(list[item]), items) == _outcome(
        lambda v, w, d: codec._check_list(item, v, w, d), items
    ), (item, items)


def test_update_columns_are_generated_from_update_stats() -> None:
    """One column per ``UpdateStats`` field, each a list of that field's own type."""
    stats = typing.get_type_hints(UpdateStats, include_extras=True)
    hints = typing.get_type_hints(UpdateColumns, include_extras=True)
    columns = {f.name: hints[f.name] for f in dataclasses.fields(UpdateColumns)}
    assert list(columns) == [f.name for f in dataclasses.fields(UpdateStats)]
    for name, hint in columns.items():
        base, _ = limits.bounds_of(hint)
        if name == "algorithm":
            (_, item) = typing.get_args(base)
            (inner,) = typing.get_args(limits.bounds_of(item)[0])
            assert inner == typing.get_args(stats[name])[0].__args__[1] | None
        else:
            assert typing.get_args(base) == (stats[name],), name


def test_a_records_new_field_is_a_column_at_once() -> None:
    """``columns_of`` reads the record's declaration: a field added there is a column, with
    its bounds, its default where a round does not fill it, and it crosses the wire."""

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Record:
        count: limits.Count
        seconds: limits.Seconds | None = None
        extra: dict[str, limits.Finite] = dataclasses.field(default_factory=dict)

    @columns_of(Record, rows=3)
    class RecordColumns(Columns[Record]):
        pass

    rows = [Record(count=1, extra={"a": 1.0}), Record(count=2, seconds=0.5)]
    columns = RecordColumns.of(rows)
    assert columns.records() == rows and columns.extra == {"a": [1.0, None]}
    assert RecordColumns.filled(2, count=[1, 2]).records() == [Record(count=1), Record(count=2)]
    checker = codec._checker(RecordColumns)
    assert checker({"count": [1], "seconds": [None], "extra": {}}, "x", 0) == RecordColumns.of(
        [Record(count=1)]
    )
    for bad, reason in [
        ({"count": [-1], "seconds": [None], "extra": {}}, "below 0"),
        ({"count": [1] * 4, "seconds": [None] * 4, "extra": {}}, "more than 3"),
        ({"count": [1], "seconds": [None], "extra": {"a": [math.inf]}}, "not finite"),
        ({"count": [1], "extra": {}}, "missing fields"),
    ]:
        with pytest.raises(ProtocolError, match=reason):
            checker(bad, "x", 0)


def test_update_columns_give_back_each_agents_record() -> None:
    """Agents may report different algorithm statistics: each gets back exactly its own, through
    the wire too, one at a time or all at once (``records``, what the server reads); ``take``
    picks rows, a slice gives the columns of its rows."""
    records = [
        STATS,
        dataclasses.replace(STATS, trajectories=3, local_wall_s=None, algorithm={}),
        dataclasses.replace(STATS, algorithm={"iw_max": 7.0, "other": -1.0}),
    ]
    columns = UpdateColumns.of(records)
    assert list(columns) == records and len(columns) == 3
    assert [columns[i] for i in range(3)] == records == columns.records()
    assert columns.algorithm == {
        "iw_mean": [1.0, None, None],
        "iw_max": [2.5, None, 7.0],
        "other": [None, None, -1.0],
    }
    batch = Update(round=2, agents=[7, 8, 9], thetas=np.zeros((3, 2), np.float32), stats=columns)
    decoded = decode(_wire(batch))
    assert isinstance(decoded, Update) and list(decoded.stats) == records
    assert list(columns.take([2, 0])) == [records[2], records[0]]
    assert list(columns[1:]) == records[1:] and isinstance(columns[1:], UpdateColumns)
    assert columns[::2].records() == records[::2] and columns[1:].algorithm["iw_mean"] == [None] * 2
    assert list(UpdateColumns.of([])) == [] and UpdateColumns.of([]).records() == []


def test_a_bad_column_is_refused_with_the_agent_row_named() -> None:
    thetas = np.zeros((2, 2), np.float32)
    good = Update(round=1, agents=[0, 1], thetas=thetas, stats=UpdateColumns.of([STATS, STATS]))
    columns = msgpack.unpackb(_wire(good)[0])["fields"]["stats"]
    for changed, reason in [
        ({"compute_s": [0.5, -1.0]}, r"stats\.compute_s\[1\]: -1\.0 is below 0"),
        ({"env_steps": [1, 2**41]}, r"stats\.env_steps\[1\]: .* is above"),
        ({"train_return": [math.nan, 1.0]}, r"stats\.train_return\[0\]: nan is not finite"),
        ({"speed": [1.0, True]}, r"stats\.speed\[1\]: must be float, got bool"),
        ({"env_steps": [1]}, "columns of different lengths"),
    ]:
        frames = _with_fields(good, stats={**columns, **changed})
        with pytest.raises(ProtocolError, match=reason) as info:
            decode(frames)
        assert info.value.code == "bad_fields"
    bad = UpdateColumns.of([STATS, dataclasses.replace(STATS, compute_s=-1.0)])
    with pytest.raises(ProtocolError, match=r"stats\.compute_s\[1\]: -1\.0 is below 0"):
        encode(dataclasses.replace(good, stats=bad))
    with pytest.raises(ValueError, match="columns of different lengths"):
        dataclasses.replace(bad, speed=[1.0])


# --- planned budgets (agents.plan) ------------------------------------------------------------


def _with_fields(message: object, **changes: Any) -> list[bytes]:
    """``message``'s frames with header fields replaced, as a faulty server would send them."""
    frames = _wire(message)
    header = msgpack.unpackb(frames[0])
    header["fields"].update(changes)
    return [msgpack.packb(header), *frames[1:]]


@pytest.mark.parametrize(
    ("message", "changes"),
    [
        (Train(round=1, theta=THETA, agents=[0]), {"budgets": [{"batch_size": 0}]}),
        (
            Train(round=1, theta=THETA, agents=[0]),
            {"budgets": [{"local_iters": protocol.MAX_BUDGET + 1}]},
        ),
        (Train(round=1, theta=THETA, agents=[0]), {"budgets": [{"batch_size": 2.5}]}),
        (Train(round=1, theta=THETA, agents=[0]), {"budgets": [{"x" * 65: 2}]}),
        (Train(round=1, theta=THETA, agents=[0]), {"budgets": [[4, 2]]}),
        (Train(round=1, theta=THETA, agents=[3, 4]), {"budgets": [{"batch_size": 4}]}),
        (Train(round=1, theta=THETA, agents=[3]), {"budgets": [{"batch_size": -1}]}),
    ],
    ids=["zero", "huge", "float", "long-key", "not-a-map", "one-short", "negative"],
)
def test_a_bad_planned_budget_is_refused(message: object, changes: dict[str, Any]) -> None:
    """The round's budget is checked as every field is: counts in [1, MAX_BUDGET], a map of
    short keys, and a batch's list one entry per agent it names."""
    with pytest.raises(ProtocolError) as info:
        decode(_with_fields(message, **changes))
    assert info.value.code == "bad_fields", str(info.value)
    with pytest.raises((ProtocolError, ValueError)):
        encode(dataclasses.replace(message, **changes))  # type: ignore[type-var]
