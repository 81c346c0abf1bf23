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
