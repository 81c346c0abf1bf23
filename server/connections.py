"""The server socket's connections, watched and bounded (a thread beside the round loop).

libzmq accepts every TCP connection and hands a multipart message to the application only once
all of its frames have arrived, so a single peer could make the server hold gigabytes (frames
each under ``ZMQ_MAXMSGSIZE``, as many as it likes) before any check of ours runs. This guard
sees the connections through a socket monitor (accepted, closed, failed handshakes) and reads
how many bytes libzmq has read on each one from the kernel (``TCP_INFO`` less the receive
queue). It closes, with ``shutdown(2)`` on libzmq's own descriptor (libzmq then drops the
connection and what it buffered):

- a connection that has received more than ``max_inflight_bytes`` since its last message was
  delivered (a message larger than any this run sends, still arriving). A registered peer's
  bytes may also be whole messages queued while the round loop is busy elsewhere (a host's
  answers come in several messages at once): its connection is closed only once the round
  loop has found the socket empty ``SETTLE_S`` after the bytes were counted, so no whole
  message of it was waiting, or at once beyond what its answers to a round could ever queue
  (its ``allowance``, at least ``QUEUED_MESSAGES`` messages' worth: a stalled round loop does
  not lift the bound). An unregistered peer has nothing to queue but a hello: at once;
- a connection that has not registered within ``hello_timeout_s`` (idle connections cost a
  descriptor each);
- connections beyond ``max_connections`` (the newest unregistered ones), so descriptors remain
  for checkpoints, metrics and the registered agents.

The round loop tells it which descriptor each message came from (``ZMQ_SRCFD``), which ones
belong to registered agents, and when it found the socket empty. Linux only (``TCP_INFO``);
elsewhere, or for IPC, only the connection count and the hello timeout apply.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import resource
import socket as pysocket
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import zmq
from zmq.utils.monitor import recv_monitor_message

logger = logging.getLogger(__name__)

WATCH_INTERVAL_S = 0.01
"""How often connections are looked at: at loopback speed a peer sends ~10-30 MB meanwhile."""
SETTLE_S = 0.05
"""A registered peer's excess bytes are judged by a drain of the socket this long after they
were counted: libzmq's I/O thread has read them by then, so a whole message among them would
have been delivered."""
QUEUED_MESSAGES = 8
"""Caps' worth of whole messages a registered peer may have queued, at the least."""
REPORT_EVERY_S = 10.0
FD_RESERVE = 64
"""Descriptors kept free of connections: files, the ZAP and monitor sockets, libzmq's own."""
_TCP_INFO = 11
_BYTES_RECEIVED_OFFSET = 128  # struct tcp_info.tcpi_bytes_received (Linux >= 4.1)
_FIONREAD = 0x541B  # bytes in a socket's receive buffer (Linux)
_EVENTS = (
    zmq.EVENT_ACCEPTED
    | zmq.EVENT_DISCONNECTED
    | zmq.EVENT_CLOSED
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
)

_libc: ctypes.CDLL | None = None
if sys.platform.startswith("linux"):
    try:
        _libc = ctypes.CDLL(None, use_errno=True)
    except OSError:  # pragma: no cover - no libc to load
        _libc = None


def _bytes_received(fd: int) -> int | None:
    """Bytes libzmq has read from this TCP socket: what the kernel has received, less what
    still waits in its receive buffer (None if not TCP, or not Linux). Bytes libzmq's I/O
    thread has not read yet (it lags on a loaded machine while a host's answers pour in) may
    hold whole messages: they are judged once read."""
    if _libc is None:
        return None
    buffer = ctypes.create_string_buffer(256)
    length = ctypes.c_uint32(256)
    if _libc.getsockopt(fd, pysocket.IPPROTO_TCP, _TCP_INFO, buffer, ctypes.byref(length)):
        return None
    if length.value < _BYTES_RECEIVED_OFFSET + 8:
        return None
    received = int(struct.unpack_from("Q", buffer.raw, _BYTES_RECEIVED_OFFSET)[0])
    unread = ctypes.c_int(0)
    if _libc.ioctl(fd, _FIONREAD, ctypes.byref(unread)):
        return received
    return received - unread.value


def _peer_name(fd: int) -> bytes | None:
    """The raw peer address of a socket: tells a descriptor number reused by libzmq for another
    connection from the one that was accepted under it."""
    if _libc is None:
        return None
    buffer = ctypes.create_string_buffer(128)
    length = ctypes.c_uint32(128)
    if _libc.getpeername(fd, buffer, ctypes.byref(length)):
        return None
    return buffer.raw[: length.value]


def _shutdown(fd: int) -> bool:
    """End a connection libzmq owns without closing its descriptor (libzmq does that)."""
    if _libc is None:
        return False
    return _libc.shutdown(fd, pysocket.SHUT_RDWR) == 0


def connection_budget(requested: int) -> int:
    """``requested``, lowered to what the process's descriptor limit leaves after the reserve."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return requested
    return max(1, min(requested, soft - FD_RESERVE))


@dataclass
class _Connection:
    fd: int
    peer: bytes | None
    accepted: float
    baseline: int = 0
    """Bytes received when its last message was delivered (or when it was accepted)."""
    delivered: int = 0
    seen_delivered: int = 0
    registered: bool = False
    over_since: float | None = None
    """When more than the cap was first counted since the last delivery (registered peers)."""
    allowance: int = 0
    """Bytes a registered peer may have in flight before it is cut without a drain."""


@dataclass
class GuardCounts:
    """What the guard did, for ``summary.json`` and the logs."""

    oversized: int = 0
    idle: int = 0
    over_budget: int = 0
    accepted: int = 0

    def as_dict(self) -> dict[str, int]:
        return {
            "closed_oversized": self.oversized,
            "closed_idle": self.idle,
            "closed_over_budget": self.over_budget,
            "connections_accepted": self.accepted,
        }


@dataclass
class ConnectionGuard:
    """Watches ``socket`` (a bound ROUTER) from its own thread until :meth:`stop`."""

    socket: zmq.Socket
    max_inflight_bytes: int
    hello_timeout_s: float
    max_connections: int
    on_handshake_failed: Callable[[int], None] = lambda value: None
    counts: GuardCounts = field(default_factory=GuardCounts)
    _connections: dict[int, _Connection] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _stopping: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None
    _monitor: zmq.Socket | None = None
    _reported_at: float = 0.0
    _reported: tuple[int, int, int] = (0, 0, 0)
    _registered_early: dict[int, int] = field(default_factory=dict)
    """Descriptors registered before the guard read their accept event."""
    _drained_at: float = float("-inf")
    _waiting: bool = False

    def start(self) -> ConnectionGuard:
        self._monitor = self.socket.get_monitor_socket(_EVENTS)
        self._thread = threading.Thread(target=self._run, name="fedhpg-connections", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        # Disable the monitor while the thread still reads it: libzmq sends each event (and the
        # last, MONITOR_STOPPED) with a blocking send under the socket's monitor lock, so an
        # event sent to a closed reader stalls its I/O thread and the next call that takes the
        # lock hangs. (A server hung so after its last round when agents left in that window.)
        if not self.socket.closed:
            with contextlib.suppress(zmq.ZMQError):
                self.socket.disable_monitor()
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._report(float("inf"))

    # -- called from the round loop's thread -----------------------------------------------

    def delivered(self, fd: int) -> None:
        """A whole message came from ``fd``."""
        connection = self._connections.get(fd)
        if connection is not None:
            connection.delivered += 1  # read by the guard thread: an int store is atomic

    def registered(self, fd: int, registered: bool, allowance: int = 0) -> None:
        """``fd``'s peer registered (or left); ``allowance``: the bytes its answers to one
        round may take (a host's: all its agents'), which it may have queued at once."""
        allowance = max(allowance, QUEUED_MESSAGES * self.max_inflight_bytes) if registered else 0
        with self._lock:
            connection = self._connections.get(fd)
            if connection is not None:
                connection.registered = registered
                connection.allowance = allowance
            elif registered and fd >= 0:  # its hello overtook the accept event
                self._registered_early[fd] = allowance
            else:
                self._registered_early.pop(fd, None)

    def drained(self) -> None:
        """The round loop found no whole message waiting."""
        self._drained_at = time.monotonic()  # a float store: atomic for the guard thread

    def waiting(self, blocked: bool) -> None:
        """The round loop blocks in a poll of the socket (True) or woke from it (False): while
        it waits, no whole message is waiting."""
        self._waiting = blocked

    def open_connections(self) -> int:
        return len(self._connections)

    # -- the guard thread ------------------------------------------------------------------

    def _run(self) -> None:
        assert self._monitor is not None
        try:
            while not self._stopping.is_set():
                try:
                    self._turn()
                except zmq.ContextTerminated:
                    break
                except Exception:  # a reader left unread would stall libzmq: outlive any bug
                    logger.exception("connection guard: an event could not be handled")
        finally:
            self._monitor.close(linger=0)

    def _turn(self) -> None:
        assert self._monitor is not None
        while self._monitor.poll(0):
            self._on_event(recv_monitor_message(self._monitor))
        self._watch(time.monotonic())
        self._monitor.poll(int(WATCH_INTERVAL_S * 1000))

    def _on_event(self, event: Mapping[str, Any]) -> None:
        kind, value = event["event"], int(event["value"])
        if kind == zmq.EVENT_ACCEPTED:
            self.counts.accepted += 1
            with self._lock:
                self._connections[value] = _Connection(
                    fd=value,
                    peer=_peer_name(value),
                    accepted=time.monotonic(),
                    baseline=_bytes_received(value) or 0,
                    registered=value in self._registered_early,
                    allowance=self._registered_early.pop(value, 0),
                )
            if len(self._connections) > self.max_connections:
                self._evict()
        elif kind in (zmq.EVENT_DISCONNECTED, zmq.EVENT_CLOSED):
            with self._lock:
                self._connections.pop(value, None)
                self._registered_early.pop(value, None)
        elif kind == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
            self.on_handshake_failed(value)

    def _evict(self) -> None:
        """Over budget: close the oldest unregistered connection (a newcomer that says hello
        at once survives a stream of idle ones)."""
        with self._lock:
            waiting = [c for c in self._connections.values() if not c.registered]
        if waiting:
            self._close(min(waiting, key=lambda c: c.accepted), "over_budget")

    def _report(self, now: float) -> None:
        """One warning per window with what was closed in it (never a line per connection)."""
        if now - self._reported_at < REPORT_EVERY_S:
            return
        current = (self.counts.oversized, self.counts.idle, self.counts.over_budget)
        closed = [now_ - before for now_, before in zip(current, self._reported, strict=True)]
        self._reported_at, self._reported = now, current
        if any(closed):
            logger.warning(
                "closed %d connections (in %.0f s or less): %d sending a message larger than "
                "%d bytes, %d not registered within %g s, %d beyond the budget of %d",
                sum(closed), REPORT_EVERY_S, closed[0], self.max_inflight_bytes, closed[1],
                self.hello_timeout_s, closed[2], self.max_connections,
            )  # fmt: skip

    def _watch(self, now: float) -> None:
        self._report(now)
        with self._lock:
            connections = list(self._connections.values())
        # a waking round loop may not have said so yet: SETTLE_S covers that latency too
        drained_at = now if self._waiting else self._drained_at
        for connection in connections:
            received = _bytes_received(connection.fd)
            if received is not None:
                if connection.delivered != connection.seen_delivered:
                    connection.seen_delivered = connection.delivered
                    connection.baseline = received
                    connection.over_since = None
                elif (over := received - connection.baseline) > self.max_inflight_bytes:
                    if connection.over_since is None:
                        connection.over_since = now
                    if (
                        not connection.registered
                        or over > connection.allowance
                        or drained_at >= connection.over_since + SETTLE_S
                    ):
                        self._close(connection, "oversized")
                        continue
            if not connection.registered and now - connection.accepted > self.hello_timeout_s:
                self._close(connection, "idle")

    def _close(self, connection: _Connection, why: str) -> None:
        with self._lock:
            if self._connections.get(connection.fd) is not connection:
                return
            del self._connections[connection.fd]
        if connection.peer is not None and _peer_name(connection.fd) != connection.peer:
            return  # the descriptor now belongs to another connection
        if not _shutdown(connection.fd):
            return
        if why == "oversized":
            self.counts.oversized += 1
        elif why == "idle":
            self.counts.idle += 1
        else:
            self.counts.over_budget += 1
