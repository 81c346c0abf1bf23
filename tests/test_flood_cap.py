"""The per-peer flood cap (server/pools/zmq_pool.py) never drops an honest host's answers.

The server handles at most ``PEER_TURN_MESSAGES`` messages of one identity per turn of its loop
and drops the rest unread, so a flooding peer cannot starve the others. An agent host of n
agents may need up to n messages to answer one request (``server.max_message_mb`` small enough
that each message carries one agent's answer): those are handled whatever the cap, while
unsolicited answers, duplicates and heartbeat floods are still cut to the cap.

- Real processes over loopback TCP: a host of 100 agents answering one agent per message, and
  a host of 150 in secure rounds (``KeyShares``, ``MaskedUpdate``, ``Unmasking`` split alike),
  every agent's answer aggregated and none dropped; in the long tier, a host of 1,000 agents.
- A pool driven by hand (the peer a raw DEALER, every burst queued before the loop's turn):
  an honest burst beyond the cap is handled whole; duplicates, answers nobody asked for and a
  heartbeat flood are dropped past the cap.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
import zmq
from procs import free_port, processes, start

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.heterogeneity.variants import range_digest
from fedhpg.common.records.types import UpdateColumns, UpdateStats
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.codec import MAX_HEADER_BYTES, decode, encode
from fedhpg.common.wire.protocol import Heartbeat, Hello, Message, Train, Update, Welcome
from fedhpg.common.wire.transport import (
    answers_per_message,
    batch_message_cap,
    max_message_bytes,
)
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.pools import zmq_pool
from fedhpg.server.pools.secure import row_bytes
from fedhpg.server.pools.zmq_pool import PEER_TURN_MESSAGES, ZmqAgentPool
from fedhpg.server.validation import UpdateCheck

TIMEOUT_S = 180
ONE_PER_MESSAGE_MB = 1.0045
"""``server.max_message_mb`` at which an ``Update`` of the default gridworld carries one agent."""


def _run_keys(k: int, max_message_mb: float) -> list[str]:
    return [
        "rounds=2", "seed=3", f"agents.num_agents={k}", "agents.budget.batch_size=[2]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
        "agents.virtual_clock=true", "eval.every=2", "eval.episodes=1",
        f"server.max_message_mb={max_message_mb}", "server.round_timeout_s=20",
        "server.register_timeout_s=120", "server.tensorboard=false",
    ]  # fmt: skip


def _host_federation(tmp_path: Path, keys: list[str], k: int) -> tuple[dict, list[list[int]]]:
    """``fedhpg-server`` and one ``fedhpg-agent`` host of agents 0..k-1; the summary and each
    round's aggregated agent indices."""
    out_dir = tmp_path / "run"
    wire = [f"server.port={free_port()}", f"server.out_dir={out_dir}"]
    with processes() as started:
        server = start(started, "fedhpg-server", [*keys, *wire], cwd=tmp_path)
        host = start(
            started, "fedhpg-agent", [*keys, *wire, "agent.first=0", f"agent.count={k}"],
            cwd=tmp_path,
        )  # fmt: skip
        _, stderr = server.communicate(timeout=TIMEOUT_S)
        assert server.returncode == 0, stderr[-3000:]
        host.wait(timeout=60)
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 2
    lines = (out_dir / "metrics.jsonl").read_text().splitlines()
    rounds = [[a["index"] for a in json.loads(line)["agents"]] for line in lines]
    return json.loads((out_dir / "summary.json").read_text()), rounds


def _num_params(keys: list[str]) -> int:
    from fedhpg.common.heterogeneity.variants import variant_of
    from fedhpg.common.learning.worker import initial_theta

    run = compose(keys)
    return int(initial_theta(variant_of(run, 0), run).numel())


def test_a_host_of_100_agents_answering_one_per_message_is_aggregated_whole(
    tmp_path: Path,
) -> None:
    k = 100
    keys = _run_keys(k, ONE_PER_MESSAGE_MB)
    d = _num_params(keys)
    cap = batch_message_cap(int(ONE_PER_MESSAGE_MB * 1024 * 1024), d)
    assert answers_per_message(cap, d) == 1  # 100 messages per round: beyond the cap
    summary, rounds = _host_federation(tmp_path, keys, k)
    assert rounds == [list(range(k))] * 2
    assert summary["dropped_flood_messages"] == 0
    assert summary["rejected_messages"] == 0 and summary["agent_deaths"] == 0
    assert sorted(summary["eval"]) == sorted(f"agent-{i}" for i in range(k))


def test_a_secure_round_of_a_host_of_150_agents_one_row_per_message(tmp_path: Path) -> None:
    """``KeyShares`` and ``MaskedUpdate`` go one agent per message (150 of each), ``Unmasking``
    two (75): ``server.max_message_mb`` is the least a secure round of 26 neighbours takes."""
    k = 150
    keys = [
        *_run_keys(k, 1.5), "privacy=secagg", "privacy.secagg.neighbours=26",
        "privacy.secagg.corruption=0.02", "privacy.secagg.dropout=0.02",
        "server.round_policy=deadline", "server.round_deadline_s=20",
    ]  # fmt: skip
    d = _num_params(keys)
    least = MAX_HEADER_BYTES + 4096 + row_bytes(compose(keys), d)
    keys = [key for key in keys if not key.startswith("server.max_message_mb=")]
    keys.append(f"server.max_message_mb={least / 2**20}")
    assert max_message_bytes(compose(keys).server) == least
    summary, rounds = _host_federation(tmp_path, keys, k)
    assert rounds == [list(range(k))] * 2
    assert summary["dropped_flood_messages"] == 0 and summary["agent_deaths"] == 0


@pytest.mark.slow
@pytest.mark.solo  # 1,000 agents' answers past the flood cap, each round within 20 s
def test_a_host_of_1000_agents_is_aggregated_whole(tmp_path: Path) -> None:
    """67 messages of 15 agents each: three past the cap."""
    k = 1000
    summary, rounds = _host_federation(tmp_path, _run_keys(k, 1.01), k)
    assert rounds == [list(range(k))] * 2
    assert summary["dropped_flood_messages"] == 0


# -- a pool driven by hand ---------------------------------------------------------------------

K = 100
D = 3
SIGNATURE = {"spaces": "x"}
DIGESTS = [f"digest-{k}" for k in range(K)]


class Wire:
    """A pool on a bound ROUTER and one registered host of all K agents on a DEALER."""

    def __init__(self) -> None:
        self.context = zmq.Context()
        self.router = self.context.socket(zmq.ROUTER)
        self.router.setsockopt(zmq.ROUTER_MANDATORY, 1)
        port = self.router.bind_to_random_port("tcp://127.0.0.1")
        settings = ServerConfig(round_timeout_s=3.0, heartbeat_interval_s=60.0)
        self.pool = ZmqAgentPool(
            socket=self.router, num_agents=K, check=UpdateCheck(num_params=D),
            env_signature=SIGNATURE, variant_digests=DIGESTS, run_settings={}, run_id="test",
            max_bytes=1 << 24, settings=settings,
        )  # fmt: skip
        self.host = self.context.socket(zmq.DEALER)
        self.host.setsockopt(zmq.LINGER, 0)
        self.host.setsockopt(zmq.IDENTITY, b"host-0-99#1")
        self.host.setsockopt(zmq.SNDHWM, 0)
        self.host.connect(f"tcp://127.0.0.1:{port}")
        hello = Hello(
            id="host-0-99", first=0, count=K, env_signature=SIGNATURE,
            variant_digest=range_digest(DIGESTS),
        )  # fmt: skip
        self.host.send_multipart(encode(hello))
        self.pool.wait_for_agents(10.0)
        assert isinstance(self.receive(), Welcome)

    def receive(self) -> Message:
        """The pool's next message to the host that is no heartbeat."""
        for _ in range(100):
            if self.host.poll(100):
                message = decode(self.host.recv_multipart())
                if not isinstance(message, Heartbeat):
                    return message
        raise AssertionError("no message from the pool")

    def burst(self, messages: list[Message]) -> None:
        """Send ``messages`` and wait until the pool's socket has them all queued (loopback:
        well within the wait), so that one turn of the loop sees them together."""
        for message in messages:
            self.host.send_multipart(encode(message))
        time.sleep(0.5)

    def close(self) -> None:
        self.host.close(linger=0)
        self.router.close(linger=0)
        self.context.term()


@pytest.fixture
def wire(monkeypatch: pytest.MonkeyPatch) -> Iterator[Wire]:
    # one turn takes every queued message (no time slice): what is dropped is the cap's doing
    monkeypatch.setattr(zmq_pool, "TURN_S", 30.0)
    opened = Wire()
    yield opened
    opened.close()


def _updates(round_index: int, agents: list[int]) -> list[Message]:
    """One ``Update`` per agent, as a host at a small ``server.max_message_mb`` sends them."""
    stats = UpdateStats(trajectories=2, env_steps=4, compute_s=0.0, train_return=0.0)
    return [
        Update(
            round=round_index,
            agents=[k],
            thetas=np.zeros((1, D), dtype=np.float32),
            stats=UpdateColumns.of([stats]),
        )
        for k in agents
    ]


def _round(
    wire: Wire, answer: Callable[[Train], list[Message]], agents: range = range(K)
) -> list[int]:
    """One round of ``agents``; ``answer`` is the host's burst; the agents aggregated."""

    def respond() -> None:
        request = wire.receive()
        assert isinstance(request, Train) and request.agents == list(agents)
        wire.burst(answer(request))

    answers = wire.pool.train(0, torch.zeros(D), agents, while_training=respond)
    return answers.result.agents


def test_an_honest_burst_beyond_the_cap_is_handled_whole(wire: Wire) -> None:
    assert K > PEER_TURN_MESSAGES
    assert _round(wire, lambda request: _updates(request.round, request.agents)) == list(range(K))
    assert wire.pool.dropped == 0


def test_duplicate_answers_are_capped(wire: Wire) -> None:
    """The honest 100 and then 300 duplicates in one burst: what the request asked for goes
    through, and of the duplicates at most what is left of that, then the cap."""
    duplicates = 300

    def answer(request: Train) -> list[Message]:
        honest = _updates(request.round, request.agents)
        return honest + _updates(request.round, list(range(K)) * 3)

    assert _round(wire, answer) == list(range(K))
    handled = K + duplicates - wire.pool.dropped
    assert handled <= K + PEER_TURN_MESSAGES, handled
    assert wire.pool.dropped >= duplicates - PEER_TURN_MESSAGES


@pytest.mark.parametrize("kind", ["answers", "heartbeats"])
def test_what_nobody_asked_for_is_capped(wire: Wire, kind: str) -> None:
    """After a round answered in full, a burst of answers (or heartbeats) gets the cap only."""
    assert _round(wire, lambda request: _updates(request.round, request.agents)) == list(range(K))
    flood = 400
    messages = _updates(0, list(range(K)) * 4) if kind == "answers" else [Heartbeat()] * flood
    wire.burst(messages)
    wire.pool.pump(1.0)
    assert wire.pool.dropped == flood - PEER_TURN_MESSAGES


def test_a_heartbeat_flood_while_answers_are_owed_is_capped(wire: Wire) -> None:
    """Heartbeats past the cap while 64 answers are owed: the request's allowance (64
    messages) is spent once, then the cap holds turn after turn; the answers still count."""
    flood, owed = 400, range(PEER_TURN_MESSAGES)

    def answer(request: Train) -> list[Message]:
        for _ in range(3):  # three turns of heartbeats: the allowance does not come back
            wire.burst([Heartbeat()] * flood)
            wire.pool.pump(1.0)
        return _updates(request.round, request.agents)

    assert _round(wire, answer, owed) == list(owed)
    assert wire.pool.dropped == 3 * (flood - PEER_TURN_MESSAGES) - len(owed)
