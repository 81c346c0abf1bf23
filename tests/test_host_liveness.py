"""An agent host stays audibly alive while it builds its agents: thousands take seconds, and
the server presumes a host silent for ``server.heartbeat_liveness`` intervals dead. The build
runs on the job thread while the main thread heartbeats; what the server sends meanwhile is
dispatched after it."""

from __future__ import annotations

import itertools
import threading
import time

import zmq

from fedhpg.agent.host import AgentHost
from fedhpg.common.configuration.run_roles import dictated_settings
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.codec import decode
from fedhpg.common.wire.protocol import Error, Heartbeat, Welcome
from fedhpg.common.wire.transport import send_message

BUILD_S = 0.8
INTERVAL_S = 0.1


def test_a_host_heartbeats_while_it_builds_its_agents() -> None:
    context = zmq.Context()
    server = context.socket(zmq.ROUTER)
    server.setsockopt(zmq.LINGER, 0)
    port = server.bind_to_random_port("tcp://127.0.0.1")
    run = compose([
        "agents.num_agents=4", "agent.first=0", "agent.count=4", f"server.port={port}",
        f"server.heartbeat_interval_s={INTERVAL_S}",
    ])  # fmt: skip
    host = AgentHost(run)
    building = threading.Event()
    build = host.work.build

    def slow_build(adopted):  # what 5,000 agents cost, on a loaded machine
        building.set()
        time.sleep(BUILD_S)
        return build(adopted)

    host.work.build = slow_build  # type: ignore[method-assign]
    heard: list[float] = []
    sent_during_build: list[Error] = []

    def serve() -> None:  # the server: counts heartbeats, speaks once while the host builds
        deadline = time.monotonic() + BUILD_S + 10
        while time.monotonic() < deadline and host.work.group is None:
            if not server.poll(50):
                continue
            identity, *frames = server.recv_multipart()
            if isinstance(decode(frames, max_bytes=1 << 20), Heartbeat) and building.is_set():
                heard.append(time.monotonic())
                if not sent_during_build:
                    sent_during_build.append(Error(code="note", reason="said during the build"))
                    send_message(server, sent_during_build[0], identity=identity)

    listener = threading.Thread(target=serve)
    listener.start()
    try:
        host.adopt(Welcome(run_id="r", first=0, count=4, run=dictated_settings(run)))
        listener.join(timeout=BUILD_S + 15)
        assert host.work.group is not None
        assert len(heard) >= BUILD_S / INTERVAL_S / 2, heard
        gaps = [b - a for a, b in itertools.pairwise(heard)]
        assert max(gaps) < 3 * INTERVAL_S, gaps
        message = host._receive()  # the server's word during the build, kept for after it
        assert isinstance(message, Error) and message.reason == "said during the build"
    finally:
        host.close()
        server.close()
        context.term()
