"""privacy= over ZeroMQ, with real sockets: secure aggregation through agent hosts and CURVE
gives the in-process θ̃ bit for bit, and a round completes, its sum exact, when 1, 10 % or
30 % of its agents drop out after sending their masked input (or before)."""

from __future__ import annotations

import subprocess
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import zmq
from procs import BIN, free_port, processes, start

from fedhpg.agent.work import AgentWork
from fedhpg.common.configuration.run_roles import adopt_settings
from fedhpg.common.learning.group import make_agent_group
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import (
    Error,
    Evaluate,
    Heartbeat,
    Hello,
    MaskRequest,
    Message,
    ShareRequest,
    Shutdown,
    Train,
    UnmaskRequest,
    Welcome,
)
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api
from fedhpg.server.metrics import read_metrics

TIMEOUT_S = 120
MAX_BYTES = 64 << 20


def _settings(k: int) -> list[str]:
    return [
        "rounds=1",
        "seed=4",
        "agents.budget.batch_size=[3]",
        "agents.budget.local_iters=[1]",
        "agents=homogeneous10",
        f"agents.num_agents={k}",
        "agents.virtual_clock=true",
        "eval.every=1",
        "eval.episodes=1",
        "privacy=secagg",
        "server.round_policy=deadline",
        "server.round_deadline_s=20",
        "server.heartbeat_interval_s=0.2",
        "server.heartbeat_liveness=15",
        "server.tensorboard=false",
    ]


class SecurePeers:
    """Lone agents on real DEALER sockets, served by one thread with the agent program's own
    work (:class:`AgentWork`): those in ``drop_after`` close their connection when asked to
    unmask, that is after their masked input went out; those in ``drop_before`` when asked for
    it. The others answer everything, heartbeat and stop at the server's shutdown."""

    def __init__(self, port: int, overrides: list[str], k: int, drop_after, drop_before) -> None:
        self.context = zmq.Context()
        self.drop_after, self.drop_before = set(drop_after), set(drop_before)
        self.works: dict[int, AgentWork] = {}
        self.hellos: dict[int, Hello] = {}
        self.refusals: list[str] = []
        self.sockets: dict[int, zmq.Socket] = {}
        base = compose(overrides)  # one composition: each agent's own differs in its index
        self.own = {i: replace(base, agent=replace(base.agent, index=i)) for i in range(k)}
        for i in range(k):
            work = AgentWork(self.own[i], range(i, i + 1), label=f"agent-{i}")
            socket = self.context.socket(zmq.DEALER)
            socket.setsockopt(zmq.IDENTITY, f"agent-{i}#peer".encode())
            socket.setsockopt(zmq.LINGER, 0)
            socket.connect(f"tcp://127.0.0.1:{port}")
            hello = Hello(
                id=f"agent-{i}",
                first=i,
                count=1,
                names_agent=True,
                env_signature=work.signature,
                variant_digest=work.digest,
                channel_keys=work.channel_keys(),
            )
            socket.send_multipart(encode(hello))
            self.works[i], self.sockets[i], self.hellos[i] = work, socket, hello
        self.dropped: list[int] = []
        self.last_beat = 0.0
        self.finished = threading.Event()
        self.errors: list[BaseException] = []
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _answer(self, i: int, message: Message) -> None:
        socket = self.sockets[i]
        if isinstance(message, Error):
            if message.code == "not_registered":  # the server was not listening yet
                socket.send_multipart(encode(self.hellos[i]))
            else:
                self.refusals.append(f"{message.code}: {message.reason}")
        elif isinstance(message, Welcome):
            self.works[i].build(adopt_settings(self.own[i], message.run))
        elif isinstance(message, UnmaskRequest | MaskRequest) and i in (
            self.drop_after if isinstance(message, UnmaskRequest) else self.drop_before
        ):
            socket.close()
            del self.sockets[i]
            self.dropped.append(i)
        elif isinstance(message, Train | ShareRequest | MaskRequest | UnmaskRequest | Evaluate):
            for answer in self.works[i].answer(message, threading.Event(), MAX_BYTES):
                socket.send_multipart(encode(answer))

    def _beat(self) -> None:
        """Every live peer's heartbeat, at most every 0.1 s: called after each message handled,
        so twenty agents' work done one after another on a loaded machine (their engines built,
        their rounds trained) never leaves one silent for the server's liveness window."""
        if time.monotonic() - self.last_beat > 0.1:
            for socket in self.sockets.values():
                socket.send_multipart(encode(Heartbeat()))
            self.last_beat = time.monotonic()

    def _loop(self) -> None:
        deadline = time.monotonic() + TIMEOUT_S
        try:
            while self.sockets and time.monotonic() < deadline:
                poller = zmq.Poller()
                for socket in self.sockets.values():
                    poller.register(socket, zmq.POLLIN)
                ready = dict(poller.poll(50))
                for i, socket in list(self.sockets.items()):
                    if socket in ready:
                        message = decode(socket.recv_multipart())
                        if isinstance(message, Shutdown):
                            socket.close()
                            del self.sockets[i]
                        else:
                            self._answer(i, message)
                        self._beat()
                self._beat()
        except BaseException as error:  # reported by the test
            self.errors.append(error)
        finally:
            self.finished.set()

    def close(self) -> None:
        self.finished.wait(timeout=TIMEOUT_S)
        for socket in self.sockets.values():
            socket.close()
        for work in self.works.values():
            work.close()
        self.context.term()


def _expected_theta(overrides: list[str], included: list[int]) -> torch.Tensor:
    """θ̃_0 plus the mean of the included agents' round-1 updates, computed here."""
    run = api.resolve_config(overrides=overrides)
    theta = api._checked(run, (), distributed=False).initial_theta
    group = make_agent_group(run, list(range(run.agents.num_agents)))
    try:
        results = group.train(1, theta, included).result
    finally:
        group.close()
    deltas = torch.stack(
        [torch.from_numpy(results.theta_of(k)).double() - theta.double() for k in included]
    )
    return (theta.double() + deltas.mean(dim=0)).float()


@pytest.mark.parametrize(
    ("k", "after", "before"),
    [
        # one agent and 10 %: the long tier (tests/test_privacy_maths.py drops them in
        # process in every run of the fast one)
        pytest.param(20, {3}, set(), marks=pytest.mark.slow),
        pytest.param(20, {4, 11}, set(), marks=pytest.mark.slow),
        # 30 %: make test-long; fast cover: tests/test_privacy_distributed.py::
        # test_a_round_completes_exactly_when_agents_drop_out[before-and-after] (drops after
        # sending too) and tests/test_privacy_maths.py (dropouts in process)
        pytest.param(20, {0, 5, 9, 13, 16, 19}, set(), marks=pytest.mark.slow),
        (20, {12}, {2, 7}),  # two never send their input, one drops after sending it
    ],
    ids=["one", "10%", "30%", "before-and-after"],
)
def test_a_round_completes_exactly_when_agents_drop_out(
    tmp_path: Path, k: int, after: set[int], before: set[int]
) -> None:
    port = free_port()
    out = tmp_path / "run"
    overrides = _settings(k)
    wire = [f"server.port={port}", f"server.out_dir={out}"]
    with processes() as started:
        server = start(started, "fedhpg-server", [*overrides, *wire], cwd=tmp_path)
        time.sleep(0.5)
        peers = SecurePeers(port, overrides, k, after, before)
        try:
            assert server.wait(timeout=TIMEOUT_S) == 0, server.stderr.read()
        finally:
            peers.close()
    assert not peers.errors, peers.errors
    assert not peers.refusals, peers.refusals
    assert sorted(peers.dropped) == sorted(after | before)
    record = read_metrics(out / "metrics.jsonl")[0]
    included = [i for i in range(k) if i not in before]
    assert record["privacy"] == {"mode": "secagg", "inputs": len(included)}
    assert [a["index"] for a in record["agents"]] == included
    theta = latest_valid_checkpoint(out / "checkpoints").theta
    if not before:  # every input is in: the in-process run's θ̃, to the bit
        assert torch.equal(theta, api.run(overrides=overrides).theta)
    assert torch.allclose(theta, _expected_theta(overrides, included), rtol=0, atol=1e-6)


def test_hosts_and_curve_give_the_in_process_theta(tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    made = subprocess.run(
        [str(BIN / "fedhpg-keys"), str(keys), "--agents", "4", "--per-host", "2"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert made.returncode == 0, made.stderr
    overrides = [
        "rounds=3",
        "seed=1",
        "agents=homogeneous4",
        "agents.budget.batch_size=[3]",
        "eval.every=3",
        "eval.episodes=2",
        "privacy=dp_secagg",
        "privacy.noise_multiplier=0.8",
        "privacy.noise_seed=9",
        "server.tensorboard=false",
    ]
    out = tmp_path / "run"
    done = subprocess.run(
        [
            str(BIN / "fedhpg-run"),
            *overrides,
            "agents.per_host=2",
            "security.curve=true",
            f"security.keys_dir={keys}",
            f"server.out_dir={out}",
            f"hydra.run.dir={out}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    assert done.returncode == 0, done.stderr
    theta = latest_valid_checkpoint(out / "checkpoints").theta
    local = api.run(overrides=overrides)
    assert torch.equal(theta, local.theta)
    records = read_metrics(out / "metrics.jsonl")
    assert [r["epsilon"] for r in records] == pytest.approx([r["epsilon"] for r in local.records])
    assert all(r["privacy"]["inputs"] == 4 for r in records)
    assert np.isfinite(records[-1]["epsilon"])


def test_an_agent_without_channel_keys_is_refused(tmp_path: Path) -> None:
    port = free_port()
    overrides = [*_settings(1), f"server.port={port}", f"server.out_dir={tmp_path / 'run'}"]
    plain = [o for o in overrides if o != "privacy=secagg"]
    with processes() as started:
        start(started, "fedhpg-server", overrides, cwd=tmp_path)
        agent = start(started, "fedhpg-agent", [*plain, "agent.index=0"], cwd=tmp_path)
        assert agent.wait(timeout=TIMEOUT_S) == 1
        assert "sent no channel keys, and this run aggregates securely" in agent.stderr.read()
