"""ZeroMQ plumbing both sides share: endpoints, socket options, framed send/receive."""

from __future__ import annotations

import logging

import zmq

from fedhpg.common.config import ServerConfig
from fedhpg.common.wire.codec import ProtocolError, decode, encode
from fedhpg.common.wire.protocol import Message

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
