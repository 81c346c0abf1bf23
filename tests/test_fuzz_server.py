"""Property-based fuzz of a live server: while a real federation runs (server and agents as
processes on loopback), ≥ 10,000 random and mutated frames hit the server's socket. The server
stays up, keeps running rounds, and the federation ends with exactly the θ of a clean run."""

from __future__ import annotations

import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
import zmq
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from peers import HonestAgent, raw_frames
from procs import free_port, processes, start, wait_until

from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.records.types import EvaluationStats, UpdateColumns, UpdateStats
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.protocol import (
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
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

FRAMES = 10_000
SEND_WAIT_MS = 60_000
HOLD_ROUND = 30
"""Agent-1 (computed in this process) holds its answer to this round until the fuzz is done,
so the run cannot end before it, however fast or slow the machine."""
TIMEOUT_S = 240
NUM_PARAMS = 25 * 4  # the demo GridWorld's tabular policy

names = st.text(max_size=12)
small_ints = st.integers(-(2**40), 2**40)
plain_values = st.recursive(
    st.none() | st.booleans() | small_ints | st.floats() | names | st.binary(max_size=16),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(names, children, max_size=3),
    max_leaves=8,
)
arrays = st.one_of(
    st.integers(0, 2 * NUM_PARAMS).map(lambda n: np.zeros(n, dtype=np.float32)),
    st.just(np.full(NUM_PARAMS, np.nan, dtype=np.float32)),
    st.just(np.ones(NUM_PARAMS, dtype=np.float64)),
    st.just(np.zeros((NUM_PARAMS, 1), dtype=np.float32)),
)
rows = st.one_of(  # an answer's [A, d]: of the run's d, or not
    st.integers(0, 2 * NUM_PARAMS).map(lambda n: np.zeros((1, n), dtype=np.float32)),
    st.just(np.full((1, NUM_PARAMS), np.nan, dtype=np.float32)),
    st.just(np.ones((1, NUM_PARAMS), dtype=np.float64)),
    st.just(np.zeros((2, NUM_PARAMS), dtype=np.float32)),
)
agents = st.lists(st.integers(-2, 4), max_size=3)
numbers = st.floats() | small_ints
stats = st.builds(
    UpdateStats,
    trajectories=small_ints,
    env_steps=small_ints,
    compute_s=numbers,
    train_return=numbers,
    grad_clipped=small_ints,
    emulated_s=numbers,
    speed=numbers,
    local_wall_s=st.none() | numbers,
    algorithm=st.dictionaries(names, st.floats(), max_size=3),
)
evaluation_stats = st.builds(
    EvaluationStats,
    return_mean=numbers,
    return_std=numbers,
    discounted_return_mean=numbers,
    success_rate=numbers,
    length_mean=numbers,
    episodes=small_ints,
)


def _hello(signature: dict[str, str]) -> st.SearchStrategy:
    # Registered ids and indices included: an impostor must be refused, never take a slot.
    return st.builds(
        Hello,
        id=st.sampled_from(["agent-0", "agent-1", "mallory", "host-0-1"]) | names,
        first=st.integers(-2, 4),
        count=st.integers(-1, 3),
        names_agent=st.booleans(),
        env_signature=st.just(signature) | st.dictionaries(names, names, max_size=2),
        variant_digest=names,
        profile=st.dictionaries(names, plain_values, max_size=2),
    )


def _messages(signature: dict[str, str]) -> st.SearchStrategy:
    rounds = st.integers(-1, 100)
    return st.one_of(
        _hello(signature),
        st.builds(
            Update,
            round=rounds,
            agents=agents,
            thetas=rows,
            stats=st.lists(stats, max_size=2).map(UpdateColumns.of),
        ),
        st.builds(
            Evaluation, round=rounds, agents=agents, stats=st.lists(evaluation_stats, max_size=2)
        ),
        st.builds(Train, round=rounds, theta=arrays, agents=agents),
        st.builds(Evaluate, round=rounds, theta=arrays, episodes=small_ints, agents=agents),
        st.builds(Welcome, run_id=names, first=small_ints, count=small_ints, run=st.just({})),
        st.builds(Error, code=names, reason=names),
        st.builds(Shutdown, reason=names),
        st.just(Heartbeat()),
    )


def _repack_header(frames: list[bytes], key: str, value: object) -> list[bytes]:
    """The message with one header entry (or one field) replaced by ``value``."""
    header = msgpack.unpackb(frames[0], raw=False)
    if key in header:
        header[key] = value
    else:
        header.setdefault("fields", {})[key] = value
    return [msgpack.packb(header, use_bin_type=True), *frames[1:]]


@st.composite
def _mutated(draw: st.DrawFn, valid: st.SearchStrategy) -> list[bytes]:
    """A valid message with one defect: a flipped byte, a cut frame, frames shuffled or
    repeated, or one header entry replaced by any msgpack value."""
    frames = draw(valid)
    how = draw(st.sampled_from(["flip", "cut", "shuffle", "header"]))
    if how == "header":
        key = draw(st.sampled_from(["v", "type", "fields", "arrays", "round", "agents", "theta"]))
        return _repack_header(frames, key, draw(plain_values))
    if how == "shuffle":
        return draw(st.permutations(frames)) + draw(st.lists(st.sampled_from(frames), max_size=2))
    index = draw(st.integers(0, len(frames) - 1))
    frame = bytearray(frames[index])
    if how == "cut":
        del frame[draw(st.integers(0, len(frame))) :]
    elif frame:
        frame[draw(st.integers(0, len(frame) - 1))] ^= draw(st.integers(1, 255))
    return [*frames[:index], bytes(frame), *frames[index + 1 :]]


def _frames(signature: dict[str, str]) -> st.SearchStrategy:
    # raw_frames, not encode: the sender applies no bounds, the server must.
    valid = _messages(signature).map(raw_frames)
    noise = st.lists(st.binary(max_size=64), min_size=1, max_size=4)
    return st.one_of(noise, valid, _mutated(valid))


def _what_went_wrong(log: str) -> str:
    """The server's log without the flood of rejected messages: the lines that say why."""
    lines = [line for line in log.splitlines() if "rejected message from" not in line]
    return "\n".join(lines[-40:])


def _fuzz_apart(port: int, signature: dict[str, str]) -> int:
    """:func:`_fuzz` in a process of its own. Hypothesis's generation holds this process's GIL
    for up to a second at a time, and agent-1 runs on a thread here: sharing the GIL, it
    could stay silent past the server's liveness window, and the server would rightly
    presume it dead."""
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=spawn) as pool:
        return pool.submit(_fuzz, port, signature).result(timeout=TIMEOUT_S * 2)


def _fuzz(port: int, signature: dict[str, str]) -> int:
    """Send FRAMES generated messages from two rogue peers; returns how many were sent."""
    context = zmq.Context()
    rogues = []
    for name in (b"fuzz#1", b"fuzz#2"):
        socket = context.socket(zmq.DEALER)
        socket.setsockopt(zmq.IDENTITY, name)
        socket.setsockopt(zmq.LINGER, 0)
        socket.connect(f"tcp://127.0.0.1:{port}")
        rogues.append(socket)
    sent = [0]

    @settings(
        max_examples=FRAMES,
        database=None,
        derandomize=True,
        deadline=None,
        phases=[Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(frames=_frames(signature), which=st.integers(0, 1))
    def send(frames: list[bytes], which: int) -> None:
        rogue = rogues[which]
        # A loaded machine makes the server slower to read: wait for room, boundedly.
        assert rogue.poll(SEND_WAIT_MS, zmq.POLLOUT), "the server stopped reading"
        rogue.send_multipart(frames, flags=zmq.NOBLOCK)
        sent[0] += 1
        while rogue.poll(0):  # read the server's answers, so they never back up
            rogue.recv_multipart()

    try:
        send()
    finally:
        for socket in rogues:
            socket.close()
        context.destroy(linger=0)
    return sent[0]


@pytest.mark.slow
@pytest.mark.solo  # rounds must go on while the fuzz floods the server
def test_live_server_survives_ten_thousand_fuzzed_frames(tmp_path: Path) -> None:
    run_keys = [
        "rounds=40", "seed=11", "agents.num_agents=2", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[2]", "agents.speeds=[1]", "agents.step_delays_s=[0.002]",
        "eval.every=10", "eval.episodes=5",
    ]  # fmt: skip
    port = free_port()
    out_dir = tmp_path / "run"
    wire = [f"server.port={port}", f"server.out_dir={out_dir}"]
    metrics = out_dir / "metrics.jsonl"
    run = compose(run_keys)
    signature = run_variants(run)[0].signature()

    def rounds_done() -> int:
        return len(metrics.read_text().splitlines()) if metrics.exists() else 0

    with processes() as started:
        server = start(started, "fedhpg-server", [*run_keys, *wire], cwd=tmp_path)
        agent = start(started, "fedhpg-agent", [*run_keys, *wire, "agent.index=0"], cwd=tmp_path)
        holder = HonestAgent(port, run, 1, hold_round=HOLD_ROUND)
        holder.thread.start()
        try:
            assert wait_until(lambda: rounds_done() >= 1, TIMEOUT_S)
            before = rounds_done()
            fuzz_started = time.monotonic()
            sent = _fuzz_apart(port, signature)
            fuzz_s = time.monotonic() - fuzz_started
            after = rounds_done()
            assert server.poll() is None, "the server is still up after the fuzz"
            holder.release.set()
            _, server_err = server.communicate(timeout=TIMEOUT_S)
            agent.wait(timeout=30)
        finally:
            holder.close()
    assert sent >= FRAMES
    assert after > before, f"rounds went on during the {fuzz_s:.0f} s fuzz ({before} → {after})"
    assert server.returncode == 0, _what_went_wrong(server_err)
    assert agent.returncode == 0 and holder.errors == []
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["rejected_messages"] >= FRAMES // 2
    assert "Traceback" not in server_err
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 40
    assert torch.equal(checkpoint.theta, run_in_process(run))
