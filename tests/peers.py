"""Peers that are not well-behaved agents, for tests against a live server (loopback only).

- :class:`ScriptedAgent`: registers as an agent and answers each Train as a script says.
- :class:`HonestAgent`: a scripted agent whose script is the real engine (a group of one
  agent): its updates and evaluations are exactly those of an ``fedhpg-agent`` process, so a
  run with it ends with the clean run's θ̃; ``after_answer`` hooks let a test add whatever it
  likes between them.
- :func:`raw_frames`: a message's frames built WITHOUT the codec's checks (for values the codec
  would refuse to send: bytes where numbers go, out-of-range numbers, oversized maps).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import torch
import zmq

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.variants import range_digest, run_variants, variant_digest
from fedhpg.common.learning.group import make_agent_group
from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import (
    MSG_TYPE_OF,
    PROTOCOL_VERSION,
    Error,
    Evaluate,
    Evaluation,
    Heartbeat,
    Hello,
    Message,
    Shutdown,
    Train,
    Welcome,
)

Frames = list[bytes]
Reply = Message | Frames


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def raw_frames(message: object, **field_overrides: Any) -> Frames:
    """``message`` on the wire as its sender wrote it, fields replaced by ``field_overrides``
    (plain msgpack values), no check of ours applied."""
    fields, descriptors, buffers = {}, [], []
    for field in dataclasses.fields(message):  # type: ignore[arg-type]
        value = getattr(message, field.name)
        if isinstance(value, np.ndarray):
            descriptors.append(
                {"field": field.name, "dtype": value.dtype.str, "shape": list(value.shape)}
            )
            buffers.append(np.ascontiguousarray(value).tobytes())
        else:
            fields[field.name] = _plain(value)
    fields.update(field_overrides)
    header = {"v": PROTOCOL_VERSION, "type": str(MSG_TYPE_OF[type(message)]), "fields": fields,
              "arrays": descriptors}  # fmt: skip
    return [msgpack.packb(header, use_bin_type=True), *buffers]


def hello_for(run: RunConfig, index: int) -> Hello:
    """The Hello a real agent ``index`` of ``run`` would send."""
    variant = run_variants(run)[index]
    return Hello(
        id=f"agent-{index}",
        first=index,
        count=1,
        names_agent=True,
        env_signature=variant.signature(),
        variant_digest=range_digest([variant_digest(run, variant)]),
    )


class ScriptedAgent:
    """A registered agent that follows a script instead of learning (a misbehaving device).

    ``answer(train) -> [replies]`` decides each round's replies (messages or raw frames; none:
    stay silent); it heartbeats like a real agent and evaluates with ``evaluate(request)``
    (fixed, well-formed statistics by default)."""

    def __init__(self, port: int, hello: Hello, answer: Callable[[Train], list[Reply]]) -> None:
        self.context = zmq.Context()
        self.socket = self.context.socket(zmq.DEALER)
        self.socket.setsockopt(zmq.IDENTITY, b"scripted#1")
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.connect(f"tcp://127.0.0.1:{port}")
        self.hello, self.answer = hello, answer
        self.errors: list[str] = []
        self.refusals: list[str] = []
        self.rounds_seen: list[int] = []
        self.shutdown: Shutdown | None = None
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def send(self, reply: Reply) -> None:
        frames = reply if isinstance(reply, list) else encode(reply)
        self.socket.send_multipart(frames)

    def evaluate(self, request: Evaluate) -> Evaluation:
        stats = EvaluationStats(
            return_mean=0.0, return_std=0.0, discounted_return_mean=0.0,
            success_rate=0.0, length_mean=1.0, episodes=1,
        )  # fmt: skip
        return Evaluation(round=request.round, agents=list(request.agents), stats=[stats])

    def after_answer(self, request: Train | Evaluate) -> None:
        """Called after each answer; a hook for tests."""

    def tick(self) -> None:
        """Called every ~0.1 s on the agent's thread; a hook for tests."""

    def _loop(self) -> None:
        self.send(self.hello)
        last_beat = time.monotonic()
        while not self.done.is_set():
            if self.socket.poll(100):
                message = decode(self.socket.recv_multipart())
                if isinstance(message, Train):
                    self.rounds_seen.append(message.round)
                    for reply in self.answer(message):
                        self.send(reply)
                    self.after_answer(message)
                elif isinstance(message, Evaluate):
                    self.send(self.evaluate(message))
                    self.after_answer(message)
                elif isinstance(message, Shutdown):
                    self.shutdown = message
                    break
                elif isinstance(message, Error):
                    self.refusals.append(message.code)
                elif not isinstance(message, Heartbeat | Welcome):
                    self.errors.append(repr(message))
            if time.monotonic() - last_beat > 0.25:
                self.send(Heartbeat())
                last_beat = time.monotonic()
            self.tick()

    def close(self) -> None:
        self.done.set()
        self.thread.join(timeout=30)
        self.socket.close()
        self.context.term()


class HonestAgent(ScriptedAgent):
    """Agent ``index`` of ``run``, computed here with the real worker: the same updates and
    evaluations as its ``fedhpg-agent`` process would send.

    ``hold_round``: its answer to that round waits until :attr:`release` is set (the server,
    with ``wait_all``, waits for it: a test can keep a run from ending before it is done)."""

    def __init__(self, port: int, run: RunConfig, index: int, hold_round: int = 0) -> None:
        self.index = index
        self.group = make_agent_group(run, [index])
        self.hold_round = hold_round
        self.held: list[Train] = []
        self.release = threading.Event()
        super().__init__(port, hello_for(run, index), self._answer)

    def _answer(self, request: Train) -> list[Reply]:
        if request.round == self.hold_round and not self.release.is_set():
            self.held.append(request)
            return []
        return self._train(request)

    def _train(self, request: Train) -> list[Reply]:
        theta = torch.from_numpy(np.array(request.theta))
        return [self.group.train(request.round, theta, [self.index]).result]

    def tick(self) -> None:
        if self.release.is_set() and self.held:
            request = self.held.pop()
            for reply in self._train(request):
                self.send(reply)
            self.after_answer(request)

    def evaluate(self, request: Evaluate) -> Evaluation:
        theta = torch.from_numpy(np.array(request.theta))
        stats = self.group.evaluate(request.round, theta, request.episodes, [self.index])
        return Evaluation(round=request.round, agents=[self.index], stats=[stats[self.index]])
