"""The agent program: registers a range of logical agents with the server, then trains and
evaluates them on request.

``fedhpg-agent agent.index=k`` serves agent k alone, ``agent.first=f agent.count=n`` the agents
f .. f+n-1 (an agent host): a lone agent is a host of one, with the same socket, registration,
messages and checks. What its agents compute, and how their devices are emulated, is
:mod:`fedhpg.agent.work`'s.

Two threads, one socket. The main thread owns the DEALER socket: it answers the server, sends a
heartbeat every ``server.heartbeat_interval_s`` and watches the server's heartbeats. Local
updates and evaluations run on a job thread, and so does the building of the agents once the
server has welcomed them, so the program stays audibly alive during a round that takes minutes
and while a host builds thousands of agents. A new request from the server supersedes the one
in flight (the server has one open request per agent): the old job is cancelled at its next
iteration or emulated-device sleep. A request the program already answered (its answer was
lost: it rejoined) is answered again from the last answers, for the agents asked. If the server
falls silent for ``heartbeat_liveness`` intervals, the program drops its work, opens a new
socket and registers again with capped exponential backoff, giving up after
``agent.connect_timeout_s``.

The routing identity is ``<id>#<nonce>``, a fresh nonce per socket: the server can tell a
second process (or a restarted one) claiming an id from the one it knows, which libzmq would
otherwise drop silently.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar, cast

import numpy as np
import zmq

from fedhpg.agent.work import AgentWork, Cancelled, OutsideRange
from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.run_roles import adopt_settings
from fedhpg.common.configuration.settings.ids import agent_id_of, host_id_of
from fedhpg.common.learning.components import agent_profile, validate_run
from fedhpg.common.learning.engine.devices import DeviceUnavailable
from fedhpg.common.runtime import timeline
from fedhpg.common.runtime.memory import freeze_setup, pin_malloc_mmap_threshold
from fedhpg.common.wire.codec import MAX_HEADER_BYTES, ProtocolError
from fedhpg.common.wire.protocol import (
    Error,
    Evaluate,
    Evaluation,
    Heartbeat,
    Hello,
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    MaskRequest,
    Message,
    Request,
    ShareRequest,
    Shutdown,
    Train,
    Unmasking,
    UnmaskRequest,
    Update,
    Welcome,
)
from fedhpg.common.wire.security import secure_agent_socket
from fedhpg.common.wire.transport import (
    configure_socket,
    connect_endpoint,
    max_message_bytes,
    send_message,
    try_decode,
)

logger = logging.getLogger(__name__)
T = TypeVar("T")

HANDSHAKE_TIMEOUT_S = 3.0
BACKOFF_INITIAL_S = 0.1
BACKOFF_MAX_S = 2.0
DUPLICATE_GRACE_LIVENESS = 1.5
"""A refused duplicate keeps trying for this many server liveness windows: if the holder of
its id is a dead predecessor, the server will have noticed by then."""


class AgentFailure(RuntimeError):
    """The agent cannot go on (refused by the server, server unreachable, ...)."""


class RunAborted(AgentFailure):
    """The server ended the run before its last round (it says why, and exits non-zero)."""


@dataclass
class Setup(Generic[T]):
    """A long set-up run on the job thread (building the agents of a host), so that the main
    thread stays audibly alive meanwhile."""

    task: Callable[[], T]
    done: threading.Event = field(default_factory=threading.Event)
    result: T | None = None
    error: BaseException | None = None


@dataclass
class Job:
    """One request being worked on by the job thread."""

    request: Request
    cancel: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)
    answers: list[Message] | None = None
    error: BaseException | None = None

    def same_request(self, request: Request) -> bool:
        return same_request(self.request, request)


def same_request(a: Request, b: Request) -> bool:
    """Whether ``b`` asks for nothing that ``a`` does not: the same round and θ̃, for a subset
    of a's agents (as when a host is asked again, after rejoining, for the answers lost)."""
    if type(a) is not type(b) or not set(b.agents) <= set(a.agents) or a.round != b.round:
        return False
    if isinstance(a, ShareRequest | MaskRequest | UnmaskRequest):  # one of each per round
        return True
    assert isinstance(b, Train | Evaluate) and isinstance(a, Train | Evaluate)
    return a.theta.shape == b.theta.shape and bool(np.array_equal(a.theta, b.theta))


def served_range(run: RunConfig) -> tuple[range, bool]:
    """The agents a program of ``run`` serves, and whether it is one agent going by its own
    id (``agent.index``) rather than an agent host (``agent.first``, ``agent.count``)."""
    agent = run.agent
    if agent.first is not None:  # validate() checked the range against agents.num_agents
        return range(agent.first, agent.first + agent.count), False
    if agent.index >= run.agents.num_agents:
        raise ConfigError(
            "agent.index",
            f"got {agent.index}, must be < agents.num_agents={run.agents.num_agents}",
        )
    return range(agent.index, agent.index + 1), True


class AgentHost:
    """The logical agents of ``run.agent`` (one, or an agent host's range) over one
    connection."""

    def __init__(self, run: RunConfig) -> None:
        self.own = run
        self.indices, self.lone = served_range(run)
        first, count = self.indices.start, len(self.indices)
        self.agent_id = (
            agent_id_of(first, run.agent.id)
            if self.lone
            else host_id_of(first, count, run.agent.id)
        )
        pin_malloc_mmap_threshold()
        self.work = AgentWork(run, self.indices, label=self.agent_id)
        self.interval_s = run.server.heartbeat_interval_s
        self.liveness_s = run.server.heartbeat_interval_s * run.server.heartbeat_liveness
        self.endpoint = connect_endpoint(run.server)
        self.max_bytes = max_message_bytes(run.server)
        self.settings: dict | None = None
        self.job: Job | None = None
        self.pending: Request | None = None
        self.last_answer: tuple[Request, list[Message]] | None = None
        self.last_heard = self.last_sent = time.monotonic()
        self.context = zmq.Context()
        self.socket = self._new_socket()
        self._wake_read, self._wake_write = os.pipe()
        self._jobs: queue.SimpleQueue[Job | Setup[Any] | None] = queue.SimpleQueue()
        self._deferred: list[Message] = []
        """The server's messages received during a set-up, dispatched after it."""
        self._job_thread = threading.Thread(
            target=self._job_loop, name=f"{self.agent_id}-jobs", daemon=True
        )
        self._job_thread.start()

    # -- the socket -------------------------------------------------------------------------

    def _new_socket(self) -> zmq.Socket:
        socket = self.context.socket(zmq.DEALER)
        socket.setsockopt(zmq.IDENTITY, f"{self.agent_id}#{os.urandom(4).hex()}".encode())
        configure_socket(socket, self.own.server)
        # Not ZMQ_IMMEDIATE: with it, the server's last messages before it closed were lost
        # in about half of our runs. Stale queued messages die with the socket on reconnect.
        socket.setsockopt(zmq.RECONNECT_IVL, int(BACKOFF_INITIAL_S * 1000))
        socket.setsockopt(zmq.RECONNECT_IVL_MAX, int(BACKOFF_MAX_S * 1000))
        # A peer that accepts TCP but never speaks ZMTP (no fedhpg server) fails the handshake
        # after this, not libzmq's 30 s: three failures give the one-line hint in seconds.
        socket.setsockopt(zmq.HANDSHAKE_IVL, int(HANDSHAKE_TIMEOUT_S * 1000))
        # CURVE client keys (if on) and a watch on the handshake: set before connecting.
        self.handshake = secure_agent_socket(socket, self.own.security, self.agent_id)
        socket.connect(self.endpoint)
        return socket

    def close(self) -> None:
        self._cancel_job()
        if self.job is not None:
            self.job.done.wait(timeout=10)
        self._jobs.put(None)
        self._job_thread.join(timeout=10)
        self.work.close()
        self._close_socket()
        self.context.term()
        os.close(self._wake_read)
        os.close(self._wake_write)

    def _close_socket(self) -> None:
        self.handshake.close()  # its monitor socket would block context.term()
        self.socket.close(linger=0)

    def _send(self, message: Message) -> bool:
        """Send without blocking; a message the socket cannot queue is dropped (heartbeats and
        hellos are repeated anyway, and an answer is resent when the server asks again)."""
        try:
            send_message(self.socket, message, block=False)
        except zmq.Again:
            return False
        self.last_sent = time.monotonic()
        return True

    def _receive(self) -> Message | None:
        """One message, if any (never blocks): those deferred during a set-up first."""
        return self._deferred.pop(0) if self._deferred else self._read()

    def _read(self) -> Message | None:
        """One message queued on the socket, if any (never blocks)."""
        try:
            frames = self.socket.recv_multipart(copy=False, flags=zmq.NOBLOCK)
        except zmq.Again:
            return None
        self.last_heard = time.monotonic()
        decoded = try_decode(frames, max_bytes=self.max_bytes)
        if isinstance(decoded, ProtocolError):
            logger.warning(
                "%s: dropped a malformed message from the server: %s", self.agent_id, decoded
            )
            return None
        return decoded

    # -- registration -----------------------------------------------------------------------

    def _hello(self) -> Hello:
        profile: dict[str, Any] = {"pid": os.getpid()}
        if self.lone:  # what it will train with: its list entries or its population's draw
            k = self.indices.start
            profile["budget"] = dataclasses.asdict(agent_profile(self.own, k).budget)
            profile["speed"] = self.work.devices[k].speed
        else:
            profile["agents"] = len(self.indices)
        return Hello(
            id=self.agent_id,
            first=self.indices.start,
            count=len(self.indices),
            names_agent=self.lone,
            env_signature=self.work.signature,
            variant_digest=self.work.digest,
            profile=profile,
            channel_keys=self.work.channel_keys(),
        )

    def _is_welcome(self, message: Message | None) -> bool:
        return (
            isinstance(message, Welcome)
            and message.first == self.indices.start
            and message.count == len(self.indices)
        )

    def register(self) -> Welcome:
        """Say hello until the server answers, backing off up to BACKOFF_MAX_S between tries."""
        hello = self._hello()
        deadline = time.monotonic() + self.own.agent.connect_timeout_s
        refusal: Error | None = None
        refused_until = float("inf")
        backoff = BACKOFF_INITIAL_S
        while time.monotonic() < min(deadline, refused_until):
            # A refused handshake (CURVE key, mechanism) shows only as a socket event.
            if (refused := self.handshake.failure()) is not None:
                raise AgentFailure(refused)
            self._send(hello)
            wait_until = time.monotonic() + backoff
            while (remaining := wait_until - time.monotonic()) > 0:
                if not self.socket.poll(int(remaining * 1000) + 1):
                    break
                reply = self._receive()
                if self._is_welcome(reply):
                    assert isinstance(reply, Welcome)
                    return reply
                if (refused := self.handshake.failure()) is not None:
                    raise AgentFailure(refused)
                if isinstance(reply, Error) and reply.code == "duplicate_agent":
                    # Our id may be held by our own dead predecessor: the server lets it go
                    # once that one has been silent for a liveness window. Keep asking a while.
                    if refusal is None:
                        refused_until = (
                            time.monotonic() + DUPLICATE_GRACE_LIVENESS * self.liveness_s
                        )
                    refusal = reply
                elif isinstance(reply, Error) and reply.code != "not_registered":
                    raise AgentFailure(
                        f"server refused registration ({reply.code}): {reply.reason}"
                    )
                elif isinstance(reply, Shutdown):
                    raise AgentFailure(f"server shut down before registration: {reply.reason}")
            backoff = min(backoff * 2, BACKOFF_MAX_S)
        if refusal is not None:
            raise AgentFailure(f"server refused registration ({refusal.code}): {refusal.reason}")
        raise AgentFailure(
            f"no answer from the server at {self.endpoint} within "
            f"{self.own.agent.connect_timeout_s:g} s (agent.connect_timeout_s)"
        )

    def adopt(self, welcome: Welcome) -> None:
        """Take the run's shared settings from the server; keep our environments and budgets."""
        self.last_heard = time.monotonic()
        if welcome.run == self.settings and self.work.group is not None:
            return  # a server we knew, restarted: same run, keep the group
        try:
            run = validate_run(adopt_settings(self.own, welcome.run))
        except ConfigError as error:
            raise AgentFailure(f"cannot take the server's settings: {error}") from None
        self._retire_job()
        try:
            group = self._set_up(lambda: self.work.build(run))
        except DeviceUnavailable as error:
            raise AgentFailure(str(error)) from None
        freeze_setup()  # the program's setup is done: the rounds' collections skip it
        needed = MAX_HEADER_BYTES + 4 * group.num_params
        if self.max_bytes < needed:
            raise AgentFailure(
                f"server.max_message_mb={self.own.server.max_message_mb:g} is below the "
                f"{needed / 2**20:.3g} MiB of this run's parameter messages"
            )
        self.settings = welcome.run
        self.last_answer = None
        self._log_registered(run, welcome.run_id)

    def _log_registered(self, run: RunConfig, run_id: str) -> None:
        first = self.indices.start
        if not self.lone:
            last = self.indices.stop - 1
            logger.debug(
                "%s registered agents %d..%d in run %s", self.agent_id, first, last, run_id
            )
            return
        profile = agent_profile(run, first)
        logger.debug(
            "%s registered in run %s (env %s, budget %s, speed=%g)",
            self.agent_id,
            run_id,
            self.work.variants[first].params,
            dataclasses.asdict(profile.budget),
            profile.speed,
        )

    def _set_up(self, task: Callable[[], T]) -> T:
        """Run ``task`` on the job thread (no job in flight) while this thread heartbeats
        every ``server.heartbeat_interval_s``: building thousands of agents takes seconds,
        and the server counts a silent host as dead. What the server sends meanwhile is
        kept for after (:meth:`_receive`)."""
        setup = Setup(task=task)
        self._jobs.put(setup)
        while not setup.done.is_set():
            now = time.monotonic()
            if now - self.last_sent >= self.interval_s:
                self._send(Heartbeat())
                self.last_sent = now
            wait_s = max(self.last_sent + self.interval_s - now, 0.0)
            if self.socket.poll(int(wait_s * 1000) + 1, zmq.POLLIN):
                while (message := self._read()) is not None:
                    self._deferred.append(message)
        os.read(self._wake_read, 64)
        self.last_heard = time.monotonic()  # the server's heartbeats were taken meanwhile
        if setup.error is not None:
            raise setup.error
        return cast(T, setup.result)

    def _reconnect(self, silent_s: float) -> None:
        logger.warning(
            "%s: no word from the server for %.1f s; reconnecting", self.agent_id, silent_s
        )
        self._cancel_job()
        self.pending = None
        self._deferred.clear()  # meant for the old connection
        self._close_socket()
        self.socket = self._new_socket()
        self.adopt(self.register())

    # -- jobs -------------------------------------------------------------------------------

    def _job_loop(self) -> None:
        """The job thread: one job at a time, for the life of the process. (One long-lived
        thread rather than one per job keeps torch's and the allocator's per-thread state.)"""
        while (job := self._jobs.get()) is not None:
            try:
                if isinstance(job, Setup):
                    job.result = job.task()
                else:
                    job.answers = self.work.answer(job.request, job.cancel, self.max_bytes)
            except BaseException as error:  # handed to the main thread, which decides
                job.error = error
            finally:
                job.done.set()
                os.write(self._wake_write, b"\0")

    def _start(self, request: Request) -> None:
        self.job = Job(request=request)
        self._jobs.put(self.job)

    def _cancel_job(self) -> None:
        if self.job is not None:
            self.job.cancel.set()

    def _retire_job(self) -> None:
        """Cancel the job in flight and wait for it to stop: the group is not shared."""
        job = self.job
        if job is not None:
            job.cancel.set()
            job.done.wait()
        self.job = None

    def _on_request(self, request: Request) -> None:
        if self.job is not None and not self.job.cancel.is_set() and self.job.same_request(request):
            return  # asked again (e.g. after we rejoined) for what we are already doing
        if self.last_answer is not None and same_request(self.last_answer[0], request):
            for answer in _resend(self.last_answer[1], request):
                self._send(answer)  # our answer was lost: send it again
            return
        if self.job is not None:
            logger.info(
                "%s: round %d superseded by a %s for round %d",
                self.agent_id,
                self.job.request.round,
                type(request).__name__,
                request.round,
            )
            self._cancel_job()
            self.pending = request
            return
        self._start(request)

    def _on_job_done(self) -> None:
        os.read(self._wake_read, 64)
        job = self.job
        if job is None or not job.done.is_set():
            return
        self.job = None
        if isinstance(job.error, Cancelled):
            pass
        elif isinstance(job.error, OutsideRange):
            raise AgentFailure(str(job.error))
        elif job.error is not None:
            raise AgentFailure(
                f"round {job.request.round} failed: {type(job.error).__name__}: {job.error}"
            ) from job.error
        elif job.answers is not None and not job.cancel.is_set():
            self.last_answer = (job.request, job.answers)
            for answer in job.answers:
                self._send(answer)
            timeline.mark(self.agent_id, "answers-sent", job.request.round)
        if self.pending is not None:
            request, self.pending = self.pending, None
            self._start(request)

    # -- the loop ---------------------------------------------------------------------------

    def _dispatch(self, message: Message) -> bool:
        """Act on one message from the server; False when the run is over."""
        if isinstance(message, Train | Evaluate | ShareRequest | MaskRequest | UnmaskRequest):
            self._on_request(message)
        elif isinstance(message, Shutdown):
            logger.debug("%s: shutdown (%s)", self.agent_id, message.reason)
            if not message.complete:
                raise RunAborted(f"the run was aborted: {message.reason}")
            return False
        elif isinstance(message, Error) and message.code == "not_registered":
            # A restarted server, or one that gave up on us: register again and carry on.
            logger.info("%s: the server does not know us; registering again", self.agent_id)
            self._send(self._hello())
        elif self._is_welcome(message):
            assert isinstance(message, Welcome)
            self.adopt(message)
        elif isinstance(message, Error):
            logger.warning(
                "%s: server reported %s: %s", self.agent_id, message.code, message.reason
            )
        elif not isinstance(message, Heartbeat):
            logger.warning("%s: ignoring unexpected %s", self.agent_id, type(message).__name__)
        return True

    def serve(self) -> None:
        """Answer the server until it says shutdown."""
        while True:
            poller = zmq.Poller()
            poller.register(self.socket, zmq.POLLIN)
            poller.register(self._wake_read, zmq.POLLIN)
            socket = self.socket
            while socket is self.socket:
                wait_s = max(self.last_sent + self.interval_s - time.monotonic(), 0.0)
                ready = dict(poller.poll(int(wait_s * 1000) + 1))
                if self._wake_read in ready:
                    self._on_job_done()
                if socket in ready or self._deferred:
                    while (message := self._receive()) is not None:
                        if not self._dispatch(message):
                            return
                now = time.monotonic()
                if now - self.last_sent >= self.interval_s:
                    self._send(Heartbeat())
                    self.last_sent = now  # even if unsent: no connection, nothing to flood
                if now - self.last_heard > self.liveness_s:
                    self._reconnect(now - self.last_heard)

    def run(self) -> None:
        started = time.monotonic()
        try:
            self.adopt(self.register())
            if not self.lone:
                logger.info(
                    "%s: %d agents registered in %.2f s",
                    self.agent_id,
                    len(self.indices),
                    time.monotonic() - started,
                )
            self.serve()
        finally:
            self.close()


def _resend(answers: list[Message], request: Request) -> list[Message]:
    """The rows of the last answers that ``request`` asks for again (a rejoined program is
    asked only for the agents whose answers the server has not got)."""
    wanted = set(request.agents)
    again: list[Message] = []
    for answer in answers:
        if isinstance(answer, MaskKeys | KeyShares | MaskedUpdate | Unmasking):
            if wanted & set(answer.agents):  # the server files the rows it still awaits
                again.append(answer)
            continue
        if not isinstance(answer, Update | Evaluation):
            continue
        rows = [i for i, k in enumerate(answer.agents) if k in wanted]
        if not rows:
            continue
        picked: dict[str, Any] = {"agents": [answer.agents[i] for i in rows]}
        if isinstance(answer, Update):
            picked["thetas"] = answer.thetas[rows]
            picked["stats"] = answer.stats.take(rows)
        else:
            picked["stats"] = [answer.stats[i] for i in rows]
        again.append(dataclasses.replace(answer, **picked))
    return again
