"""Registration over real sockets (server/pools/links.py), one message family for every
placement: a lone agent is a range of one that goes by its own id, a host's agents are
``agent-<k>``; a range held by a live link is a duplicate; a buffered server takes ranges of
one only. The pool is driven by hand (no agent processes)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import pytest
import zmq

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.heterogeneity.variants import range_digest
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import Error, Heartbeat, Hello, Message, Welcome
from fedhpg.server.pools.zmq_pool import ZmqAgentPool
from fedhpg.server.validation import UpdateCheck

K = 4
DIGESTS = [f"digest-{k}" for k in range(K)]
SIGNATURE = {"spaces": "x"}


class Wire:
    """A pool on a bound ROUTER, and DEALERs that speak to it."""

    def __init__(self, settings: ServerConfig) -> None:
        self.context = zmq.Context()
        self.router = self.context.socket(zmq.ROUTER)
        self.router.setsockopt(zmq.ROUTER_MANDATORY, 1)
        self.port = self.router.bind_to_random_port("tcp://127.0.0.1")
        self.pool = ZmqAgentPool(
            socket=self.router, num_agents=K, check=UpdateCheck(num_params=3),
            env_signature=SIGNATURE, variant_digests=DIGESTS, run_settings={}, run_id="test",
            max_bytes=1 << 24, settings=settings,
        )  # fmt: skip
        self.dealers: list[zmq.Socket] = []

    def ask(self, identity: bytes, hello: Hello) -> Message:
        """Send ``hello`` from a new connection; the pool's first reply that is no heartbeat."""
        dealer = self.context.socket(zmq.DEALER)
        dealer.setsockopt(zmq.LINGER, 0)
        dealer.setsockopt(zmq.IDENTITY, identity)
        dealer.connect(f"tcp://127.0.0.1:{self.port}")
        self.dealers.append(dealer)
        dealer.send_multipart(encode(hello))
        for _ in range(50):
            self.pool.pump(0.1)
            while dealer.poll(0):
                reply = decode(dealer.recv_multipart())
                if not isinstance(reply, Heartbeat):
                    return reply
        raise AssertionError("no reply")

    def close(self) -> None:
        for dealer in self.dealers:
            dealer.close(linger=0)
        self.router.close(linger=0)
        self.context.term()


@pytest.fixture
def wire() -> Iterator[Wire]:
    opened = Wire(ServerConfig())
    yield opened
    opened.close()


def _hello(name: str, first: int, count: int = 1, *, names_agent: bool = False) -> Hello:
    return Hello(
        id=name,
        first=first,
        count=count,
        names_agent=names_agent,
        env_signature=SIGNATURE,
        variant_digest=range_digest(DIGESTS[first : first + count]),
    )


def test_a_lone_agent_and_hosts_register_with_one_hello(wire: Wire) -> None:
    alice = wire.ask(b"alice#1", _hello("alice", 0, names_agent=True))
    assert isinstance(alice, Welcome) and (alice.first, alice.count) == (0, 1)
    host = wire.ask(b"host-1-2#1", _hello("host-1-2", 1, 2))
    assert isinstance(host, Welcome) and (host.first, host.count) == (1, 2)
    lone_host = wire.ask(b"host-3-3#1", _hello("host-3-3", 3))  # a host of one
    assert isinstance(lone_host, Welcome)
    assert wire.pool.agent_ids == ["alice", "agent-1", "agent-2", "agent-3"]


@pytest.mark.parametrize(
    ("hello", "code"),
    [
        (_hello("mallory", 1, 2, names_agent=True), "bad_fields"),  # one name for two agents
        (_hello("mallory", 3, 2), "bad_index"),  # beyond the run's agents
        (dataclasses.replace(_hello("mallory", 0, 2), env_signature={}), "env_signature"),
        (dataclasses.replace(_hello("mallory", 0, 2), variant_digest="other"), "variant_mismatch"),
    ],
    ids=["named-host", "beyond", "spaces", "variants"],
)
def test_a_hello_the_run_cannot_take_is_refused_with_a_reason(
    wire: Wire, hello: Hello, code: str
) -> None:
    reply = wire.ask(b"mallory#1", hello)
    assert isinstance(reply, Error) and reply.code == code, reply
    assert wire.pool.agent_ids == []


def test_a_range_or_a_name_held_by_a_live_link_is_a_duplicate(wire: Wire) -> None:
    assert isinstance(wire.ask(b"alice#1", _hello("alice", 1, names_agent=True)), Welcome)
    for identity, hello in [
        (b"host-0-1#1", _hello("host-0-1", 0, 2)),  # overlaps alice's index
        (b"alice#2", _hello("alice", 2, names_agent=True)),  # alice's name at another index
    ]:
        reply = wire.ask(identity, hello)
        assert isinstance(reply, Error) and reply.code == "duplicate_agent", reply
    assert wire.pool.agent_ids == ["alice"]


def test_a_buffered_server_takes_ranges_of_one_only() -> None:
    wire = Wire(ServerConfig(round_policy="buffered"))
    try:
        host = wire.ask(b"host-0-1#1", _hello("host-0-1", 0, 2))
        assert isinstance(host, Error) and host.code == "unsupported", host
        assert "one Train carries one round index" in host.reason
        assert isinstance(wire.ask(b"host-0-0#1", _hello("host-0-0", 0)), Welcome)
        assert isinstance(wire.ask(b"agent-1#1", _hello("agent-1", 1, names_agent=True)), Welcome)
    finally:
        wire.close()
