"""A server under resource attacks, in one federation (real processes, loopback TCP):

1. 2,000 idle TCP connections while the server runs with ``ulimit -n 1024``;
2. a 2 GiB multipart message (2,048 frames of 1 MiB, each under the per-frame cap);
3. a 20 s flood of heartbeats from an unregistered peer;

and, all along, a registered agent (agent-1, computed in this process with the real worker)
that sends 10,000 structure-aware fuzzed messages between its honest answers. The server's RSS
stays under its figure before the attacks + 200 MB, rounds keep completing, no honest agent is
presumed dead or reconnects, the server never holds more than 1,024 descriptors, and the run
ends with exactly the clean run's θ̃. Every loop here is bounded in count and time.
"""

from __future__ import annotations

import json
import os
import resource
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
import torch
import zmq
from peers import HonestAgent
from procs import BIN, QUIET, free_port, processes, start, wait_until
from wire_fuzz import frames_of, generate

from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.codec import encode
from fedhpg.common.wire.protocol import Evaluate, Heartbeat, Train
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

ROUNDS = 150
FUZZ_MESSAGES = 10_000
IDLE_CONNECTIONS = 2_000
FD_LIMIT = 1024
MULTIPART_FRAMES, FRAME_BYTES = 2048, 1 << 20
FLOOD_S = 20.0
RSS_MARGIN = 200 << 20
TIMEOUT_S = 300
RUN = [
    f"rounds={ROUNDS}", "seed=13", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0.002]",
    "eval.every=10", "eval.episodes=4", "server.hello_timeout_s=3",
]  # fmt: skip


def _rss(pid: int) -> int:
    with open(f"/proc/{pid}/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def _fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


class Watch(threading.Thread):
    """Samples the server's RSS and descriptor count every 20 ms."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self.pid, self.peak_rss, self.peak_fds = pid, 0, 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.02):
            try:
                self.peak_rss = max(self.peak_rss, _rss(self.pid))
                self.peak_fds = max(self.peak_fds, _fds(self.pid))
            except OSError:
                return


class Fuzzer(HonestAgent):
    """Agent-1: its honest answer, then its share of the fuzz, for the round just answered (so
    every fuzzed update or evaluation is late for the server: none can be averaged)."""

    def __init__(self, port: int, run, messages: list) -> None:
        super().__init__(port, run, 1)
        self.queue = messages
        self.per_answer = len(messages) // (ROUNDS + ROUNDS // 10) + 1
        self.sent = 0

    def after_answer(self, request: Train | Evaluate) -> None:
        for message, overrides in self.queue[self.sent : self.sent + self.per_answer]:
            frames = frames_of(message, overrides, request.round)
            if frames is not None:
                self.send(frames)
        self.sent = min(self.sent + self.per_answer, len(self.queue))


def _rounds(metrics: Path) -> int:
    return len(metrics.read_text().splitlines()) if metrics.exists() else 0


@pytest.mark.slow
@pytest.mark.solo  # counts rounds in timed windows and the flood's messages sent
def test_resource_attacks_leave_the_run_intact(tmp_path: Path) -> None:
    port = free_port()
    out_dir = tmp_path / "run"
    metrics = out_dir / "metrics.jsonl"
    wire = [f"server.port={port}", f"server.out_dir={out_dir}"]
    run = compose(RUN)
    num_params = 100
    signature = run_variants(run)[0].signature()
    fuzz = generate(FUZZ_MESSAGES, num_params, signature)
    context = zmq.Context()

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT, FD_LIMIT))

    with processes() as started:
        server = subprocess.Popen(
            [str(BIN / "fedhpg-server"), *RUN, *wire], stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, cwd=tmp_path, env={**os.environ, **QUIET},
            preexec_fn=limited,
        )  # fmt: skip
        started.append(server)
        agent = start(started, "fedhpg-agent", [*RUN, *wire, "agent.index=0"], cwd=tmp_path)
        fuzzer = Fuzzer(port, run, fuzz)
        fuzzer.thread.start()
        watch = Watch(server.pid)
        try:
            assert wait_until(lambda: _rounds(metrics) >= 3, 60), "the federation never started"
            baseline = _rss(server.pid)
            watch.start()

            # 1. idle connections, beyond the descriptor limit
            idle = []
            for _ in range(IDLE_CONNECTIONS):
                connection = socket.socket()
                connection.setblocking(False)
                connection.connect_ex(("127.0.0.1", port))
                idle.append(connection)
            rounds_before = _rounds(metrics)
            time.sleep(5.0)
            idle_rounds = _rounds(metrics) - rounds_before
            for connection in idle:
                connection.close()
            assert server.poll() is None, "the server survived the idle connections"

            # 2. a 2 GiB multipart message, every frame under the per-frame cap
            big = context.socket(zmq.DEALER)
            big.setsockopt(zmq.LINGER, 0)
            big.connect(f"tcp://127.0.0.1:{port}")
            frame = memoryview(bytearray(FRAME_BYTES))
            header = encode(Heartbeat())[0]
            big.send(header, zmq.SNDMORE)
            for i in range(MULTIPART_FRAMES):
                big.send(frame, zmq.SNDMORE if i < MULTIPART_FRAMES - 1 else 0, copy=False)
            time.sleep(5.0)
            big.close()
            assert server.poll() is None, "the server survived the 2 GiB message"

            # 3. a 20 s flood from one unregistered peer
            flood = context.socket(zmq.DEALER)
            flood.setsockopt(zmq.LINGER, 0)
            flood.setsockopt(zmq.SNDHWM, 100_000)
            flood.connect(f"tcp://127.0.0.1:{port}")
            beat = encode(Heartbeat())
            rounds_before, sent = _rounds(metrics), 0
            flood_end = time.monotonic() + FLOOD_S
            while time.monotonic() < flood_end:
                try:
                    flood.send_multipart(beat, flags=zmq.NOBLOCK)
                    sent += 1
                except zmq.Again:
                    flood.poll(10, zmq.POLLOUT)
                while flood.poll(0):
                    flood.recv_multipart()
            flood_rounds = _rounds(metrics) - rounds_before
            flood.close()

            _, server_err = server.communicate(timeout=TIMEOUT_S)
            _, agent_err = agent.communicate(timeout=60)
        finally:
            watch.stop.set()
            fuzzer.close()
            context.destroy(linger=0)
    assert server.returncode == 0, server_err[-3000:]
    assert agent.returncode == 0, agent_err[-2000:]
    assert fuzzer.sent >= FUZZ_MESSAGES and fuzzer.errors == []
    assert idle_rounds >= 2 and flood_rounds >= 5, (idle_rounds, flood_rounds)
    assert sent > 50_000, f"the flood sent only {sent} messages"
    assert watch.peak_rss < baseline + RSS_MARGIN, (
        f"server RSS peaked at {watch.peak_rss >> 20} MiB, {baseline >> 20} MiB before"
    )
    assert watch.peak_fds < FD_LIMIT, watch.peak_fds
    assert "presumed dead" not in server_err and "reconnecting" not in agent_err
    assert "Traceback" not in server_err
    assert "more warnings about peers' messages" in server_err, "the suppressed count is told"
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["closed_oversized"] >= 1
    # More connections were accepted (and closed) than the descriptor limit could have held.
    assert summary["closed_idle"] + summary["closed_over_budget"] >= FD_LIMIT
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == ROUNDS
    assert torch.equal(checkpoint.theta, run_in_process(run))
    print(
        f"\nrss before {baseline >> 20} MiB, peak {watch.peak_rss >> 20} MiB; peak descriptors "
        f"{watch.peak_fds}; rounds during idle 5 s: {idle_rounds}, during the 20 s flood: "
        f"{flood_rounds} ({sent} messages); closed: {summary['closed_idle']} idle, "
        f"{summary['closed_over_budget']} over budget, {summary['closed_oversized']} oversized"
    )
