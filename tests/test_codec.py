"""The wire codec: exact round trips of every message type, and no input that can make
decode fail with anything but a ProtocolError (property-based fuzzing)."""

from __future__ import annotations

import contextlib

import msgpack
import numpy as np
import pytest
import zmq
from hypothesis import given, settings
from hypothesis import strategies as st

from fedhpg.common.codec import ProtocolError, decode, encode
from fedhpg.common.protocol import (
    PAYLOAD_TYPES,
    Error,
    Evaluate,
    Evaluation,
    Heartbeat,
    Hello,
    Shutdown,
    Train,
    Update,
    Welcome,
)

THETA = np.random.default_rng(0).standard_normal(1000).astype(np.float32)
SAMPLES = [
    Hello(
        agent_id="agent-0",
        agent_index=0,
        env_signature={"observation": "Discrete(25)"},
        profile={"speed": 0.5},
    ),
    Welcome(run_id="abc", agent_index=3, run={"seed": 1, "algo": {"name": "fedhpg"}}),
    Train(round=7, theta=THETA),
    Update(round=7, theta=THETA, stats={"trajectories": 10, "compute_s": 0.5, "extra": [1, 2]}),
    Evaluate(round=9, theta=THETA, episodes=20),
    Evaluation(round=9, stats={"return_mean": -1.5, "success_rate": 1.0}),
    Heartbeat(),
    Shutdown(reason="run complete"),
    Error(code="bad_update", reason="parameters contain NaN or Inf"),
]


def _equal(a: object, b: object) -> bool:
    if type(a) is not type(b):
        return False
    for name, value in vars(a).items():
        other = getattr(b, name)
        if isinstance(value, np.ndarray):
            if (
                value.dtype != other.dtype
                or value.shape != other.shape
                or value.tobytes() != other.tobytes()
            ):
                return False
        elif value != other:
            return False
    return True


def test_every_message_type_has_a_sample() -> None:
    assert {type(m) for m in SAMPLES} == set(PAYLOAD_TYPES.values())


@pytest.mark.parametrize("message", SAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(message: object) -> None:
    frames = encode(message)  # type: ignore[arg-type]
    assert _equal(decode([bytes(f) for f in frames]), message)


@pytest.mark.parametrize("dtype", ["float32", "float64", "int64", "uint8", "bool"])
@pytest.mark.parametrize("shape", [(0,), (), (3, 4), (1_000_000,)])
def test_arrays_round_trip_bit_exactly(dtype: str, shape: tuple[int, ...]) -> None:
    array = (np.arange(int(np.prod(shape))) % 7).astype(dtype).reshape(shape)
    decoded = decode([bytes(f) for f in encode(Train(round=1, theta=array))])
    assert decoded.theta.dtype == array.dtype and decoded.theta.shape == shape  # type: ignore[union-attr]
    assert decoded.theta.tobytes() == array.tobytes()  # type: ignore[union-attr]


def test_non_contiguous_arrays_are_sent_contiguously() -> None:
    array = np.arange(20, dtype=np.float32).reshape(4, 5)[:, ::2]
    decoded = decode([bytes(f) for f in encode(Train(round=1, theta=array))])
    np.testing.assert_array_equal(decoded.theta, array)  # type: ignore[union-attr]


def _header(**overrides: object) -> bytes:
    header = {
        "v": 1,
        "type": "train",
        "fields": {"round": 1},
        "arrays": [{"field": "theta", "dtype": "<f4", "shape": [2]}],
    }
    header.update(overrides)
    return msgpack.packb(header)


GOOD_ARRAY = np.zeros(2, dtype=np.float32).tobytes()


@pytest.mark.parametrize(
    ("frames", "code"),
    [
        ([], "malformed"),
        ([b"\xc1"], "malformed"),
        ([msgpack.packb([1, 2])], "malformed"),
        ([msgpack.packb({"v": 1})], "malformed"),
        ([_header(v=2), GOOD_ARRAY], "version"),
        ([_header(type="nope"), GOOD_ARRAY], "unknown_type"),
        ([_header(fields={}), GOOD_ARRAY], "bad_fields"),
        ([_header(fields={"round": 1, "extra": 2}), GOOD_ARRAY], "bad_fields"),
        ([_header(fields={"round": "1"}), GOOD_ARRAY], "bad_fields"),
        ([_header(fields={"round": True}), GOOD_ARRAY], "bad_fields"),
        ([_header()], "bad_array"),
        ([_header(), GOOD_ARRAY, GOOD_ARRAY], "bad_array"),
        (
            [_header(arrays=[{"field": "theta", "dtype": "|O", "shape": [2]}]), GOOD_ARRAY],
            "bad_array",
        ),
        (
            [_header(arrays=[{"field": "theta", "dtype": "<f4", "shape": [-2]}]), GOOD_ARRAY],
            "bad_array",
        ),
        (
            [_header(arrays=[{"field": "theta", "dtype": "<f4", "shape": [3]}]), GOOD_ARRAY],
            "bad_array",
        ),
        (
            [_header(arrays=[{"field": "other", "dtype": "<f4", "shape": [2]}]), GOOD_ARRAY],
            "bad_array",
        ),
        ([msgpack.packb(msgpack.ExtType(1, b"x"))], "malformed"),
    ],
)
def test_rejections_carry_a_code(frames: list[bytes], code: str) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(frames)
    assert info.value.code == code, str(info.value)


def test_size_cap() -> None:
    frames = [bytes(f) for f in encode(Train(round=1, theta=np.zeros(1000, dtype=np.float32)))]
    with pytest.raises(ProtocolError) as info:
        decode(frames, max_bytes=1000)
    assert info.value.code == "too_large"


def _valid_frames() -> st.SearchStrategy[list[bytes]]:
    return st.sampled_from([[bytes(f) for f in encode(m)] for m in SAMPLES])


@st.composite
def mutated(draw: st.DrawFn) -> list[bytes]:
    frames = list(draw(_valid_frames()))
    kind = draw(st.sampled_from(["flip", "truncate", "drop", "extra", "header"]))
    index = draw(st.integers(0, len(frames) - 1))
    if kind == "flip" and frames[index]:
        data = bytearray(frames[index])
        position = draw(st.integers(0, len(data) - 1))
        data[position] ^= draw(st.integers(1, 255))
        frames[index] = bytes(data)
    elif kind == "truncate":
        frames[index] = frames[index][: draw(st.integers(0, max(len(frames[index]) - 1, 0)))]
    elif kind == "drop":
        del frames[index]
    elif kind == "extra":
        frames.insert(index, draw(st.binary(max_size=64)))
    else:
        header = msgpack.unpackb(frames[0])
        key = draw(st.sampled_from(sorted(header)))
        header[key] = draw(
            st.recursive(
                st.none()
                | st.booleans()
                | st.integers(-(2**63), 2**64 - 1)
                | st.floats()
                | st.text(max_size=8)
                | st.binary(max_size=8),
                lambda children: (
                    st.lists(children, max_size=3)
                    | st.dictionaries(st.text(max_size=5), children, max_size=3)
                ),
                max_leaves=6,
            )
        )
        frames[0] = msgpack.packb(header)
    return frames


@settings(max_examples=3000, deadline=None, derandomize=True)
@given(st.one_of(st.lists(st.binary(max_size=128), max_size=4), mutated()))
def test_fuzz_decode_only_ever_raises_protocol_error(frames: list[bytes]) -> None:
    with contextlib.suppress(ProtocolError):
        decode(frames)


def test_over_real_sockets() -> None:
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    dealer = context.socket(zmq.DEALER)
    try:
        for sock in (router, dealer):
            sock.setsockopt(zmq.LINGER, 0)
        port = router.bind_to_random_port("tcp://127.0.0.1")
        dealer.setsockopt(zmq.IDENTITY, b"agent-0#1")
        dealer.connect(f"tcp://127.0.0.1:{port}")
        dealer.send_multipart(encode(SAMPLES[3]), copy=False)
        assert router.poll(5000)
        identity, *frames = router.recv_multipart(copy=False)
        assert identity.bytes == b"agent-0#1"
        assert _equal(decode(frames), SAMPLES[3])
    finally:
        router.close()
        dealer.close()
        context.term()
