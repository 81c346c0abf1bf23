"""Hostile peers and unlucky operators against real processes on loopback: no
registered agent can crash or poison the server, no operator mistake loses data or ends in a
traceback. Every process is killed at the end, pass or fail; every wait is bounded."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import resource
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
import torch
from peers import HonestAgent, raw_frames
from procs import BIN, QUIET, free_port, processes, start, start_federation, wait_until

from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.protocol import Train, Update
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

TIMEOUT_S = 120
RUN = [
    "seed=5", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "eval.every=3", "eval.episodes=4",
]  # fmt: skip
FAST = "agents.step_delays_s=[0.001]"
SLOW = "agents.step_delays_s=[0.004]"


def _lines(result: subprocess.CompletedProcess) -> list[str]:
    return [line for line in result.stderr.splitlines() if line.strip()]


def _digests(directory: Path) -> dict[str, str]:
    """Every file below ``directory`` by content: proof that a refusal touched nothing."""
    return {
        str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def test_a_registered_agent_can_neither_crash_nor_poison_the_server(tmp_path: Path) -> None:
    """Agent-1 answers every round with a poisoned update before its honest one: bytes where a
    number goes (crashed the server's metrics writer), 1e39 and 2**63 trajectories (turned
    θ̃ into NaN under strategy=weighted), ~1 MB of statistics (written to metrics.jsonl). Each is
    refused at decoding; the honest update is averaged; the run ends with the clean θ̃."""
    run_keys = [*RUN, FAST, "rounds=5", "strategy=weighted"]
    out_dir = tmp_path / "run"
    port = free_port()
    wire = [f"server.port={port}", f"server.out_dir={out_dir}"]
    run = compose(run_keys)
    poisons = [
        {"algorithm": {"iw_mean": b"\x00" * 16}},
        {"trajectories": 1e39},
        {"trajectories": 2**63},
        {"algorithm": {f"stat{i:05d}": 1.0 for i in range(40_000)}},
        {"train_return": math.nan},
    ]

    class Poisoner(HonestAgent):
        def _train(self, request: Train) -> list:
            honest = super()._train(request)
            update = honest[0]
            assert isinstance(update, Update)
            poison = poisons[(request.round - 1) % len(poisons)]
            # the one row's columns, one of them poisoned
            columns = {
                name: {key: [item] for key, item in value.items()}
                if name == "algorithm"
                else [value]
                for name, value in poison.items()
            }
            stats = dataclasses.asdict(update.stats) | columns
            return [raw_frames(update, stats=stats), *honest]

    with processes() as started:
        server = start(started, "fedhpg-server", [*run_keys, *wire], cwd=tmp_path)
        peer = Poisoner(port, run, 1)
        peer.thread.start()
        try:
            agent = start(
                started, "fedhpg-agent", [*run_keys, *wire, "agent.index=0"], cwd=tmp_path
            )
            _, server_err = server.communicate(timeout=TIMEOUT_S)
            agent.wait(timeout=30)
        finally:
            peer.close()
    assert server.returncode == 0, server_err[-3000:]
    assert agent.returncode == 0 and "Traceback" not in server_err
    assert peer.refusals.count("bad_fields") + peer.refusals.count("too_large") == 5
    assert peer.shutdown is not None and peer.shutdown.complete
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["rejected_messages"] == 5
    records = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    assert all(len(json.dumps(r)) < 20_000 for r in records), "no peer fills metrics.jsonl"
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 5
    assert torch.isfinite(checkpoint.theta).all()
    assert torch.equal(checkpoint.theta, run_in_process(run))


def _finished_run(tmp_path: Path) -> Path:
    out_dir = tmp_path / "run"
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), *RUN, FAST, "rounds=4", f"server.out_dir={out_dir}",
         f"hydra.run.dir={tmp_path / 'hydra'}"],
        capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path,
        env={**os.environ, **QUIET},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    return out_dir


def _server(tmp_path: Path, *args: str, delays: str = FAST) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "fedhpg-server"), *RUN, delays, f"server.port={free_port()}",
         "server.register_timeout_s=5", *args],
        capture_output=True, text=True, timeout=60, cwd=tmp_path, env={**os.environ, **QUIET},
    )  # fmt: skip


@pytest.mark.slow
def test_operator_mistakes_end_in_one_line_and_touch_nothing(tmp_path: Path) -> None:
    out_dir = _finished_run(tmp_path)
    before = _digests(out_dir)
    cases = [
        (["rounds=4", f"server.out_dir={out_dir}"], "holds a run already"),
        (["rounds=2", f"server.out_dir={out_dir}", "resume=true"], "rounds: got 2"),
        (["rounds=4", f"server.out_dir={out_dir / 'metrics.jsonl'}"], "is a file"),
        (["rounds=4", f"server.out_dir={tmp_path / 'new'}", "server.max_message_mb=0.0001"],
         "server.max_message_mb: got 0.0001, below"),
    ]  # fmt: skip
    for args, message in cases:
        result = _server(tmp_path, *args)
        lines = _lines(result)
        assert result.returncode == 2 and len(lines) == 1 and message in lines[0], (args, lines)
    assert _digests(out_dir) == before
    assert not (tmp_path / "new" / "metrics.jsonl").exists()

    metrics = out_dir / "metrics.jsonl"
    for damage, where in (
        (lambda lines: lines[:1] + lines[2:], "line 2 is not round 2's record"),
        (lambda lines: [*lines[:3], lines[3][: len(lines[3]) // 2]], "line 4 is not a JSON"),
    ):
        original = metrics.read_bytes()
        metrics.write_text("\n".join(damage(original.decode().splitlines())) + "\n")
        damaged = _digests(out_dir)
        result = _server(tmp_path, "rounds=6", f"server.out_dir={out_dir}", "resume=true")
        lines = _lines(result)
        assert result.returncode == 2 and len(lines) == 1 and where in lines[0], lines
        assert _digests(out_dir) == damaged, "a refused resume writes nothing"
        metrics.write_bytes(original)


@pytest.mark.slow
@pytest.mark.solo  # a second server's start-up races the live run's last rounds
def test_a_second_server_cannot_take_a_live_run_directory(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    port = free_port()
    run_keys = [*RUN, SLOW, "rounds=16"]
    wire = [f"server.port={port}", f"server.out_dir={out_dir}"]
    metrics = out_dir / "metrics.jsonl"
    with processes() as started:
        server, agents = start_federation(started, [*run_keys, *wire], 2, cwd=tmp_path)
        assert wait_until(
            lambda: metrics.exists() and len(metrics.read_text().splitlines()) >= 3, 60
        )
        second = _server(tmp_path, "rounds=30", f"server.out_dir={out_dir}", "resume=true",
                         delays=SLOW)  # fmt: skip
        _, server_err = server.communicate(timeout=TIMEOUT_S)
        for agent in agents:
            agent.wait(timeout=30)
    lines = _lines(second)
    assert second.returncode == 2 and len(lines) == 1 and "is in use by another" in lines[0]
    assert f"pid {server.pid}" in lines[0]
    assert server.returncode == 0, server_err[-2000:]
    rounds = [json.loads(line)["round"] for line in metrics.read_text().splitlines()]
    assert rounds == list(range(1, 17)), "the live run lost nothing"


def test_a_full_disk_stops_the_run_cleanly_and_the_agents_say_so(tmp_path: Path) -> None:
    """RLIMIT_FSIZE stands in for a full disk (writes past it fail with EFBIG, as with
    ENOSPC): the server stops with one line and exit 1, leaves no temporary file and a valid
    checkpoint; the agents exit 1 saying the run was aborted."""
    out_dir = tmp_path / "run"
    port = free_port()
    args = [*RUN, FAST, "rounds=200", f"server.port={port}", f"server.out_dir={out_dir}"]

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (24 * 1024, 24 * 1024))

    with processes() as started:
        server = subprocess.Popen(
            [str(BIN / "fedhpg-server"), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, cwd=tmp_path, env={**os.environ, **QUIET}, preexec_fn=small_files,
        )  # fmt: skip
        started.append(server)
        agents = [
            start(started, "fedhpg-agent", [*args, f"agent.index={k}"], cwd=tmp_path)
            for k in range(2)
        ]
        _, server_err = server.communicate(timeout=TIMEOUT_S)
        agent_errs = [agent.communicate(timeout=30)[1] for agent in agents]
    lines = [line for line in server_err.splitlines() if line.strip()]
    assert server.returncode == 1 and "Traceback" not in server_err, server_err[-2000:]
    assert "File too large" in lines[-1] and "cannot write" in lines[-1]
    assert list(out_dir.rglob("*.tmp")) == []
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and 1 <= checkpoint.round < 200
    for agent, err in zip(agents, agent_errs, strict=True):
        assert agent.returncode == 3 and "the run was aborted" in err, err[-1000:]


@pytest.mark.slow
def test_counters_survive_a_resume(tmp_path: Path) -> None:
    import zmq

    out_dir = tmp_path / "run"
    port = free_port()
    run_keys = [*RUN, SLOW, "rounds=12"]
    wire = [f"server.port={port}", f"server.out_dir={out_dir}"]
    metrics = out_dir / "metrics.jsonl"
    context = zmq.Context()
    try:
        with processes() as started:
            server, agents = start_federation(started, [*run_keys, *wire], 2, cwd=tmp_path)
            assert wait_until(lambda: metrics.exists() and metrics.read_text().strip(), 60)
            rogue = context.socket(zmq.DEALER)
            rogue.setsockopt(zmq.LINGER, 0)
            rogue.connect(f"tcp://127.0.0.1:{port}")
            for _ in range(50):
                rogue.send(b"\x00junk")
            done = len(metrics.read_text().splitlines())
            assert wait_until(lambda: len(metrics.read_text().splitlines()) >= done + 2, 60)
            server.send_signal(signal.SIGKILL)
            server.wait(timeout=10)
            rogue.close()
            checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
            assert checkpoint is not None
            before = checkpoint.state["counters"]["rejected_messages"]
            restarted = start(started, "fedhpg-server", [*run_keys, *wire, "resume=true"],
                              cwd=tmp_path)  # fmt: skip
            _, err = restarted.communicate(timeout=TIMEOUT_S)
            for agent in agents:
                agent.wait(timeout=30)
    finally:
        context.destroy(linger=0)
    assert restarted.returncode == 0, err[-2000:]
    assert before >= 50, "the junk was counted before the kill"
    # After the restart only the agents' few unregistered heartbeats add to it.
    assert json.loads((out_dir / "summary.json").read_text())["rejected_messages"] >= before


@pytest.mark.slow
@pytest.mark.solo  # gives up within 30 s, timed
def test_an_agent_pointed_at_no_fedhpg_server_says_so_quickly(tmp_path: Path) -> None:
    """A port where something accepts TCP but never speaks ZMTP: one line, long before
    agent.connect_timeout_s (60 s)."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(listener.accept()[0])
            except TimeoutError:
                continue

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        started = time.monotonic()
        result = subprocess.run(
            [str(BIN / "fedhpg-agent"), *RUN, FAST, f"server.port={listener.getsockname()[1]}"],
            capture_output=True, text=True, timeout=60, cwd=tmp_path,
        )  # fmt: skip
        took = time.monotonic() - started
    finally:
        stop.set()
        thread.join(timeout=5)
        for connection in held:
            connection.close()
        listener.close()
    lines = _lines(result)
    assert result.returncode == 1 and len(lines) == 1, lines
    assert "no fedhpg server (check server.host and server.port)" in lines[0]
    assert took < 30
