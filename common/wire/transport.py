"""ZeroMQ plumbing both sides share: endpoints, socket options, framed send/receive."""

from __future__ import annotations

import logging

import zmq

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.wire.codec import MAX_HEADER_BYTES, ProtocolError, decode, encode
from fedhpg.common.wire.protocol import BATCH_THETA_BYTES, MAX_BATCH_ANSWERS, Message

logger = logging.getLogger(__name__)


def bind_endpoint(server: ServerConfig) -> str:
    if server.transport == "ipc":
        return f"ipc://{server.ipc_path}"
    host = "0.0.0.0" if server.bind_all else server.host
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"tcp://{host}:{server.port or '*'}"


def connect_endpoint(server: ServerConfig) -> str:
    if server.transport == "ipc":
        return f"ipc://{server.ipc_path}"
    host = server.host
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"tcp://{host}:{server.port}"


def max_message_bytes(server: ServerConfig) -> int:
    return int(server.max_message_mb * 1024 * 1024)


def single_message_bytes(num_params: int) -> int:
    """The largest message one agent sends: a header of up to 1 MiB and θ_k as float32."""
    return MAX_HEADER_BYTES + 4 * num_params + 4096


def batch_message_cap(configured: int, num_params: int) -> int:
    """The largest message of a run of ``num_params`` parameters, host batches included: one
    θ at least; at most ``MAX_BATCH_ANSWERS`` θs, within ``BATCH_THETA_BYTES`` more and the
    configured ``server.max_message_mb``. Server and hosts compute it alike."""
    single = single_message_bytes(num_params)
    extra = min(BATCH_THETA_BYTES, 4 * num_params * (MAX_BATCH_ANSWERS - 1))
    return max(single, min(configured, single + extra))


def answers_per_message(cap: int, num_params: int) -> int:
    """Agents per ``Update`` that keep it under ``cap`` (at least one)."""
    room = (cap - MAX_HEADER_BYTES - 4096) // (4 * max(num_params, 1))
    return max(1, min(MAX_BATCH_ANSWERS, room))


def configure_socket(socket: zmq.Socket, server: ServerConfig) -> None:
    """Options every fedhpg socket gets: no lingering on close, a message size cap, IPv6."""
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.MAXMSGSIZE, max_message_bytes(server))
    socket.setsockopt(zmq.IPV6, 1)


def send_message(
    socket: zmq.Socket, message: Message, *, identity: bytes | None = None, block: bool = True
) -> None:
    """Send one message. ``block=False`` raises ``zmq.Again`` instead of waiting on a peer
    whose queue is full (or, on a DEALER with ZMQ_IMMEDIATE, when no connection is up)."""
    frames = encode(message)
    if identity is not None:
        frames = [identity, *frames]
    socket.send_multipart(frames, copy=False, flags=0 if block else zmq.NOBLOCK)


def receive_frames(socket: zmq.Socket) -> list[zmq.Frame]:
    return socket.recv_multipart(copy=False)


def try_decode(frames: list[zmq.Frame], *, max_bytes: int) -> Message | ProtocolError:
    """Decode, turning any malformed input into a ProtocolError value (never raising)."""
    try:
        return decode(frames, max_bytes=max_bytes)
    except ProtocolError as error:
        return error
