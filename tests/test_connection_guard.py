"""The connection guard's socket monitor must never block libzmq.

libzmq sends monitor events with a blocking send while holding the socket's monitor lock: an
event sent after the guard's reader is gone (or while nobody reads it) stalls libzmq's I/O
thread, and the next call that takes the lock (``disable_monitor``, closing the socket) hangs
for good, with the GIL held. A server used to hang so after its last round, now and then (3 in
40 runs), when agents disconnected between the guard's stop and ``disable_monitor``.

Each scenario runs in a forked child with a deadline, so a regression fails the test instead of
hanging the test run.
"""

from __future__ import annotations

import multiprocessing
import os
import resource
import socket as pysocket
import struct
import threading
import time
from collections.abc import Callable

import zmq

from fedhpg.server.connections import ConnectionGuard

PEERS_PER_BURST = 20
MAX_PEERS_PER_CHURN = 4000
# Closed sockets are reaped by libzmq's threads later: a churn faster than the reaper piles up
# file descriptors and socket slots until a new socket fails with EMFILE (seen in CI on 2 busy
# cores). The churn waits while this many descriptors are open: under half the process's limit
# and under libzmq's 1023 sockets (each holds at least one descriptor), a burst's worth spare.
MAX_OPEN_FDS = min(resource.getrlimit(resource.RLIMIT_NOFILE)[0] // 2, 800)
TRIES = 12
SCENARIO_DEADLINE_S = 60.0


def _guarded_router(context: zmq.Context) -> tuple[zmq.Socket, str, ConnectionGuard]:
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    guard = ConnectionGuard(
        router, max_inflight_bytes=1 << 20, hello_timeout_s=30.0, max_connections=1000
    ).start()
    port = router.bind_to_random_port("tcp://127.0.0.1")
    return router, f"tcp://127.0.0.1:{port}", guard


def _serves(context: zmq.Context, router: zmq.Socket, endpoint: str) -> bool:
    """A new peer's message arrives (libzmq's I/O thread is not stalled)."""
    peer = context.socket(zmq.DEALER)
    peer.setsockopt(zmq.LINGER, 0)
    try:
        peer.connect(endpoint)
        peer.send(b"ping")
        if not router.poll(3000):
            return False
        router.recv_multipart()
        return True
    finally:
        peer.close()


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _churn(context: zmq.Context, endpoint: str, until: threading.Event) -> None:
    """Connections opened and closed as fast as the reaper allows: a stream of monitor events,
    bounded in count and in the descriptors it holds."""
    for _ in range(MAX_PEERS_PER_CHURN // PEERS_PER_BURST):
        if until.is_set():
            return
        while _open_fds() > MAX_OPEN_FDS and not until.is_set():
            time.sleep(0.001)
        for _ in range(PEERS_PER_BURST):
            peer = context.socket(zmq.DEALER)
            peer.setsockopt(zmq.LINGER, 0)
            peer.connect(endpoint)
            peer.send(b"x")
            peer.close()


def _in_child(scenario: Callable[[], None]) -> None:
    """Run ``scenario`` in a forked process; fail if it fails or outlives the deadline."""

    def body() -> None:
        try:
            scenario()
        except AssertionError as error:
            print(f"FAILED: {error}", flush=True)  # the child's stdout is the test's output
            raise SystemExit(1) from None
        raise SystemExit(0)

    child = multiprocessing.get_context("fork").Process(target=body)
    child.start()
    child.join(SCENARIO_DEADLINE_S)
    if child.is_alive():
        child.kill()
        child.join()
        raise AssertionError(f"hung for {SCENARIO_DEADLINE_S:g} s (libzmq blocked)")
    assert child.exitcode == 0, f"the scenario failed (exit {child.exitcode}); see its output"


def _failing_handler() -> None:
    context = zmq.Context()
    router, endpoint, guard = _guarded_router(context)
    calls = []

    def broken(event: object) -> None:
        calls.append(event)
        raise RuntimeError("a bug in an event handler")

    guard._on_event = broken  # type: ignore[method-assign]
    for attempt in range(3):  # the first event raises; later ones must still flow
        assert _serves(context, router, endpoint), f"peer {attempt}: the socket stalled"
    deadline = time.monotonic() + 5.0  # the guard reads events every few milliseconds
    while len(calls) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(calls) >= 3, "the guard stopped reading events after a failing handler"
    guard.stop()
    router.close()
    context.term()


def _stop_during_churn() -> None:
    for _ in range(TRIES):
        context = zmq.Context()
        router, endpoint, guard = _guarded_router(context)
        stop_churn = threading.Event()
        churn = threading.Thread(target=_churn, args=(context, endpoint, stop_churn), daemon=True)
        churn.start()
        time.sleep(0.02)
        guard.stop()
        stop_churn.set()
        churn.join(10.0)
        assert _serves(context, router, endpoint), "the socket stalled after the guard stopped"
        router.close()
        context.term()


def test_a_failing_event_handler_does_not_stall_the_socket() -> None:
    _in_child(_failing_handler)


def test_stopping_the_guard_while_peers_come_and_go_never_hangs() -> None:
    """12 tries, each stopping a guard while a churn of connections sends it events; the socket
    must then still serve, close and terminate."""
    _in_child(_stop_during_churn)


def _round_loop(router: zmq.Socket, guard: ConnectionGuard, seconds: float) -> list[list[bytes]]:
    """What the server's round loop does with the guard for ``seconds``: poll (saying it
    waits), receive each whole message (saying where it came from), say when it found the
    socket empty."""
    messages: list[list[bytes]] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        guard.waiting(True)
        ready = router.poll(10)
        guard.waiting(False)
        if not ready:
            guard.drained()
            continue
        while True:
            try:
                frames = router.recv_multipart(copy=False, flags=zmq.NOBLOCK)
            except zmq.Again:
                guard.drained()
                break
            guard.delivered(int(frames[1].get(zmq.SRCFD)))
            messages.append([frame.bytes for frame in frames[1:]])
    return messages


def _guarded(cap: int) -> tuple[zmq.Context, zmq.Socket, str, ConnectionGuard]:
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    guard = ConnectionGuard(
        router, max_inflight_bytes=cap, hello_timeout_s=30.0, max_connections=100
    ).start()
    port = router.bind_to_random_port("tcp://127.0.0.1")
    return context, router, f"tcp://127.0.0.1:{port}", guard


def _registered_peer(
    context: zmq.Context, router: zmq.Socket, endpoint: str, guard: ConnectionGuard
) -> zmq.Socket:
    """A DEALER whose hello the round loop has taken and registered (by its ZMQ_SRCFD)."""
    peer = context.socket(zmq.DEALER)
    peer.setsockopt(zmq.LINGER, 0)
    peer.connect(endpoint)
    peer.send(b"hello")
    assert router.poll(3000), "the hello never arrived"
    frames = router.recv_multipart(copy=False)
    fd = int(frames[1].get(zmq.SRCFD))
    guard.delivered(fd)
    guard.registered(fd, True)
    return peer


CAP = 256 << 10


def _queued_while_the_loop_is_busy() -> None:
    """A registered peer sends many whole messages, more bytes than the in-flight cap, while the
    round loop is busy elsewhere: they queue in libzmq, none is oversized."""
    context, router, endpoint, guard = _guarded(CAP)
    peer = _registered_peer(context, router, endpoint, guard)
    for _ in range(24):
        peer.send(bytes(64 << 10))  # 1.5 MiB in all, six times the cap
    time.sleep(0.5)  # the round loop aggregates, writes a checkpoint, ... (no receive)
    received = len(_round_loop(router, guard, 1.0))
    assert guard.counts.oversized == 0, "a peer's queued whole messages were taken as one"
    assert received == 24, f"{received} of 24 messages arrived"
    guard.stop()
    peer.close()
    router.close()
    context.term()


class _RawPeer:
    """A DEALER spoken by hand (ZMTP 3.0, NULL mechanism) over a plain TCP socket, so that a
    multipart message can arrive slowly: libzmq's own sockets send a message only once its last
    frame is queued."""

    def __init__(self, endpoint: str) -> None:
        host, port = endpoint.removeprefix("tcp://").rsplit(":", 1)
        self.socket = pysocket.create_connection((host, int(port)), timeout=5.0)
        greeting = b"\xff" + bytes(8) + b"\x7f" + bytes([3, 0]) + b"NULL".ljust(20, b"\0")
        self.socket.sendall(greeting + bytes(32))
        self._read(64)  # the server's greeting
        ready = b"\x05READY" + b"\x0bSocket-Type" + struct.pack(">I", 6) + b"DEALER"
        self.socket.sendall(bytes([0x04, len(ready)]) + ready)
        flags, size = self._read(2)  # the server's READY, a short command
        assert flags == 0x04, f"the server answered with flags {flags:#x}"
        self._read(size)

    def _read(self, count: int) -> bytes:
        data = b""
        while len(data) < count:
            chunk = self.socket.recv(count - len(data))
            assert chunk, "the server closed the connection during the handshake"
            data += chunk
        return data

    def send_frame(self, body: bytes, more: bool) -> bool:
        """False once the server has cut the connection."""
        header = bytes([0x03 if more else 0x02]) + struct.pack(">Q", len(body))
        try:
            self.socket.sendall(header + body)
            return True
        except OSError:
            return False

    def close(self) -> None:
        self.socket.close()


def _send_slowly(peer: _RawPeer, frames: int, frame_bytes: int, gap_s: float) -> None:
    """One multipart message, a frame every ``gap_s``, until the server cuts it."""
    for i in range(frames):
        if not peer.send_frame(bytes(frame_bytes), more=i < frames - 1):
            return
        time.sleep(gap_s)


def _oversized_from_a_registered_peer() -> None:
    """A registered peer's one message larger than the cap, every frame small, is cut while
    the round loop waits, and never delivered; so is an unregistered peer's."""
    context, router, endpoint, guard = _guarded(CAP)
    peer, stranger = _RawPeer(endpoint), _RawPeer(endpoint)
    peer.send_frame(b"hello", more=False)
    assert router.poll(3000), "the hello never arrived"
    frames = router.recv_multipart(copy=False)
    guard.delivered(int(frames[1].get(zmq.SRCFD)))
    guard.registered(int(frames[1].get(zmq.SRCFD)), True)
    # 1 MiB each over ~0.3 s: four times the cap, arriving for many of the guard's looks
    senders = [
        threading.Thread(target=_send_slowly, args=(sender, 64, 16 << 10, 0.005))
        for sender in (peer, stranger)
    ]
    for sender in senders:
        sender.start()
    delivered = _round_loop(router, guard, 1.0)
    for sender in senders:
        sender.join(5.0)
    assert guard.counts.oversized == 2, guard.counts
    assert delivered == [], f"{len(delivered)} oversized messages were delivered"
    guard.stop()
    peer.close()
    stranger.close()
    router.close()
    context.term()


def _beyond_the_allowance_while_the_loop_is_stalled() -> None:
    """A registered peer's message still arriving past its allowance is cut though the round
    loop never drains the socket (a stalled loop does not lift the bound)."""
    context, router, endpoint, guard = _guarded(CAP)
    peer = _RawPeer(endpoint)
    peer.send_frame(b"hello", more=False)
    assert router.poll(3000), "the hello never arrived"
    fd = int(router.recv_multipart(copy=False)[1].get(zmq.SRCFD))
    guard.delivered(fd)
    guard.registered(fd, True)  # allowance: QUEUED_MESSAGES caps, 2 MiB
    sender = threading.Thread(target=_send_slowly, args=(peer, 64, 64 << 10, 0.005))
    sender.start()  # 4 MiB over ~0.3 s
    sender.join(10.0)  # the round loop is busy all along: no poll, no drain
    deadline = time.monotonic() + 2.0
    while guard.counts.oversized == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert guard.counts.oversized == 1, guard.counts
    assert _round_loop(router, guard, 0.3) == [], "the cut message was delivered"
    guard.stop()
    peer.close()
    router.close()
    context.term()


def test_whole_messages_queued_while_the_loop_is_busy_are_not_oversized() -> None:
    _in_child(_queued_while_the_loop_is_busy)


def test_an_oversized_message_is_cut_from_registered_and_unregistered_peers() -> None:
    _in_child(_oversized_from_a_registered_peer)


def test_a_registered_peer_past_its_allowance_is_cut_without_a_drain() -> None:
    _in_child(_beyond_the_allowance_while_the_loop_is_stalled)


def test_a_registration_before_the_accept_event_is_kept() -> None:
    """The round loop may register a peer whose accept event the guard has not read yet (its
    hello came first): the registration must hold, or the peer is cut as idle."""
    guard = ConnectionGuard(
        socket=None,  # type: ignore[arg-type]  # only the bookkeeping is exercised
        max_inflight_bytes=CAP, hello_timeout_s=0.0, max_connections=100,
    )  # fmt: skip
    guard.registered(7, True, allowance=10 * CAP)
    guard._on_event({"event": zmq.EVENT_ACCEPTED, "value": 7})
    assert guard._connections[7].registered
    assert guard._connections[7].allowance == 10 * CAP
    guard._on_event({"event": zmq.EVENT_CLOSED, "value": 7})
    guard._on_event({"event": zmq.EVENT_ACCEPTED, "value": 7})  # another connection, same fd
    assert not guard._connections[7].registered


def test_bytes_still_in_the_kernel_are_not_counted_as_read() -> None:
    """What the guard counts on a connection is what libzmq has read: bytes waiting in the
    kernel's receive buffer (libzmq's I/O thread lagging on a loaded machine) may be whole
    messages it has not reached yet, so they are not yet "in flight"."""
    from fedhpg.server.connections import _bytes_received

    listener = pysocket.create_server(("127.0.0.1", 0))
    sender = pysocket.create_connection(listener.getsockname())
    receiver, _ = listener.accept()
    try:
        sender.sendall(bytes(100_000))
        time.sleep(0.1)  # arrived in the receive buffer, not read
        assert _bytes_received(receiver.fileno()) == 0
        read = 0
        while read < 40_000:
            read += len(receiver.recv(40_000 - read))
        assert _bytes_received(receiver.fileno()) == 40_000
    finally:
        for end in (sender, receiver, listener):
            end.close()
