"""Transport security: CURVE encryption and key-based authentication of agents (off by default).

With ``security.curve=true`` the server's ROUTER socket is a CURVE server, and a ZAP handler
(pyzmq's :class:`~zmq.auth.thread.ThreadAuthenticator`) admits only the public keys found in the
allow-list directory. Each allow-list file binds its key to a name and to the agents it may
speak for (:class:`KeyBinding`): ``agent-3.key`` is agent 3 alone, ``host-0-2.key`` the host of
agents 0..2, ``alice@5.key`` the agent ``alice`` at index 5, ``rack@0-99.key`` the host
``rack`` of agents 0..99. The binding becomes the connection's ZAP User-Id, and the server
refuses any hello (and any later message) whose id or agent range differs from it, exactly
(error code :data:`KEY_MISMATCH`): a key cannot register another index or a wider range.
Each agent's DEALER socket is a CURVE client with its own key pair and the server's public
key; a monitor on it turns a refused handshake into one clear error instead of a silent wait.

``fedhpg-keys`` (:mod:`fedhpg.server.commands.keys`) writes the files this module reads. Everything
the entry points need lives here, so that the wiring into the server, the pool and the agent is a
few call lines:

* server: :func:`secure_server_socket` before ``bind`` (returns a :class:`ServerGuard` to stop);
* pool: :func:`key_mismatch` on every decoded message;
* agent: :func:`secure_agent_socket` before ``connect`` (returns a :class:`HandshakeWatch`);
* launcher: :func:`check_launch_keys` before forking.
"""

from __future__ import annotations

import atexit
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils import z85
from zmq.utils.monitor import recv_monitor_message

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.key_names import KeyBinding, parse_binding
from fedhpg.common.configuration.placement import agents_per_host, host_ranges
from fedhpg.common.configuration.settings.ids import agent_id_of, host_id_of
from fedhpg.common.configuration.settings.privacy import SecurityConfig

logger = logging.getLogger(__name__)

SERVER_KEY_NAME = "server"
PUBLIC_SUFFIX = ".key"
SECRET_SUFFIX = ".key_secret"
ALLOWED_DIR = "allowed"
KEY_MISMATCH = "key_mismatch"
"""Error code: a message whose agent id is not the name bound to the connection's key."""

NO_DETAIL_FAILURES = 3
"""Handshakes failing without detail in a row before an agent gives up (one can be a reset)."""
LOG_EVERY_S = 60.0
"""A repeated refusal (same key, same error) is a warning at most this often, else debug: a
refused peer retries every few seconds."""


@dataclass(frozen=True, kw_only=True)
class KeyPair:
    """A CURVE key pair, both halves z85-encoded (40 characters each)."""

    public: bytes
    secret: bytes


def _fail(key: str, message: str) -> NoReturn:
    raise ConfigError(key, message)


def _read_key_file(path: Path, key: str) -> tuple[bytes, bytes | None]:
    """(public, secret or None) from a zmq certificate file, as z85; ConfigError otherwise."""
    if not path.exists():
        _fail(key, f"{path}: no such key file (generate keys with fedhpg-keys)")
    if not path.is_file():
        _fail(key, f"{path}: is not a key file")
    try:
        public, secret = zmq.auth.load_certificate(path)
    except OSError as error:
        _fail(key, f"{path}: cannot read ({error.strerror or error})")
    except ValueError:
        _fail(key, f"{path}: not a CURVE key file (no public-key line)")
    for half in (public, secret):
        if half is not None and not _is_z85_key(half):
            _fail(key, f"{path}: not a CURVE key file (a key is not 40 z85 characters)")
    return public, secret


def _is_z85_key(text: bytes) -> bool:
    if len(text) != 40:
        return False
    try:
        return len(z85.decode(text)) == 32
    except (ValueError, KeyError, IndexError, TypeError):  # z85.decode's ways of saying no
        return False


def load_secret_key(path: str | Path, key: str) -> KeyPair:
    """The key pair in a ``*.key_secret`` file; ``key`` names the setting for errors."""
    public, secret = _read_key_file(Path(path), key)
    if secret is None:
        _fail(key, f"{path}: holds no secret key (the .key_secret file is needed here)")
    if zmq.curve_public(secret) != public:
        _fail(key, f"{path}: its public and secret keys do not belong together")
    return KeyPair(public=public, secret=secret)


def load_public_key(path: str | Path, key: str) -> bytes:
    """The public key in a ``*.key`` file (z85)."""
    public, secret = _read_key_file(Path(path), key)
    if secret is not None:
        _fail(key, f"{path}: is a secret key file; give the public .key file")
    return public


def load_allow_list(directory: str | Path, key: str) -> dict[bytes, KeyBinding]:
    """{public key (z85): its binding} from the ``*.key`` files of the allow-list."""
    folder = Path(directory)
    if not folder.is_dir():
        _fail(key, f"{folder}: no such allow-list directory")
    bindings: dict[bytes, KeyBinding] = {}
    names: dict[str, Path] = {}
    for path in sorted(folder.glob(f"*{PUBLIC_SUFFIX}")):
        public = load_public_key(path, key)
        binding = parse_binding(path.name[: -len(PUBLIC_SUFFIX)])
        if isinstance(binding, str):
            _fail(key, f"{path}: {binding}")
        if public in bindings:
            _fail(key, f"{path}: the same key is also allowed as {bindings[public].describe()}")
        if binding.name in names:
            _fail(key, f"{path}: {binding.name!r} is also allowed by {names[binding.name]}")
        bindings[public], names[binding.name] = binding, path
    if not bindings:
        _fail(key, f"{folder}: the allow-list holds no <agent id>{PUBLIC_SUFFIX} files")
    return bindings


def _path(security: SecurityConfig, key: str, default: str) -> tuple[Path, str]:
    """Where a key file is and which setting to name when it is wrong."""
    explicit = getattr(security, key)
    if explicit is not None:
        return Path(explicit), f"security.{key}"
    if security.keys_dir is None:
        _fail(f"security.{key}", "CURVE is on: set it, or security.keys_dir")
    return Path(security.keys_dir) / default, "security.keys_dir"


def validate_security(security: SecurityConfig) -> None:
    """The checks that hold for every role: called where a config is validated.

    Each explicitly given file is loaded and checked. Files found through ``keys_dir`` are
    checked where they are used (the server needs its own, an agent its own), by
    :func:`server_keys` and :func:`agent_keys`, with the same one-line errors.
    """
    if not security.curve:
        return
    if not zmq.has("curve"):
        _fail("security.curve", "this libzmq was built without CURVE support")
    explicit = (
        security.server_secret_key,
        security.allowed_keys_dir,
        security.server_public_key,
        security.agent_secret_key,
    )
    if security.keys_dir is None and all(p is None for p in explicit):
        _fail(
            "security.keys_dir",
            "CURVE is on (security.curve=true) but no keys are given: set security.keys_dir "
            "to the directory written by fedhpg-keys",
        )
    if security.keys_dir is not None and not Path(security.keys_dir).is_dir():
        _fail("security.keys_dir", f"{security.keys_dir}: no such directory")
    if security.server_secret_key is not None:
        load_secret_key(security.server_secret_key, "security.server_secret_key")
    if security.agent_secret_key is not None:
        load_secret_key(security.agent_secret_key, "security.agent_secret_key")
    if security.server_public_key is not None:
        load_public_key(security.server_public_key, "security.server_public_key")
    if security.allowed_keys_dir is not None:
        load_allow_list(security.allowed_keys_dir, "security.allowed_keys_dir")


@dataclass(frozen=True, kw_only=True)
class ServerKeys:
    own: KeyPair
    allowed: dict[bytes, KeyBinding]
    """{agent public key (z85): who it speaks for}."""
    allowed_dir: Path


def server_keys(security: SecurityConfig) -> ServerKeys:
    """The server's key pair and allow-list; ConfigError naming the setting if one is wrong."""
    secret_path, secret_key = _path(security, "server_secret_key", SERVER_KEY_NAME + SECRET_SUFFIX)
    allowed_path, allowed_key = _path(security, "allowed_keys_dir", ALLOWED_DIR)
    return ServerKeys(
        own=load_secret_key(secret_path, secret_key),
        allowed=load_allow_list(allowed_path, allowed_key),
        allowed_dir=allowed_path,
    )


@dataclass(frozen=True, kw_only=True)
class AgentKeys:
    own: KeyPair
    server_public: bytes


def agent_keys(security: SecurityConfig, agent_id: str) -> AgentKeys:
    """Agent ``agent_id``'s key pair and the server's public key."""
    secret_path, secret_key = _path(security, "agent_secret_key", agent_id + SECRET_SUFFIX)
    public_path, public_key = _path(security, "server_public_key", SERVER_KEY_NAME + PUBLIC_SUFFIX)
    return AgentKeys(
        own=load_secret_key(secret_path, secret_key),
        server_public=load_public_key(public_path, public_key),
    )


def check_launch_keys(run: RunConfig) -> None:
    """``fedhpg-run`` forks the server and K agents from one config: check every key first, so a
    missing one is a one-line error before anything starts, not a failed child."""
    security = run.security
    if not security.curve:
        return
    if security.agent_secret_key is not None and run.agents.num_agents > 1:
        _fail(
            "security.agent_secret_key",
            "fedhpg-run starts every agent, each with its own key: use security.keys_dir",
        )
    server = server_keys(security)
    per_host = agents_per_host(run)
    if per_host > 1:  # each host has one connection, one key, named by its id
        wanted = [
            KeyBinding(host_id_of(f, c), range(f, f + c))
            for f, c in host_ranges(run.agents.num_agents, per_host)
        ]
    else:
        wanted = [KeyBinding(agent_id_of(k), range(k, k + 1)) for k in range(run.agents.num_agents)]
    for binding in wanted:
        keys = agent_keys(security, binding.name)
        if keys.server_public != server.own.public:
            _fail("security.server_public_key", "is not the public half of the server's key")
        allowed = server.allowed.get(keys.own.public)
        if allowed != binding:
            as_what = "not allowed" if allowed is None else f"allowed as {allowed.describe()}"
            _fail(
                "security.allowed_keys_dir",
                f"{server.allowed_dir}: {binding.name}'s public key is {as_what}, "
                f"not as {binding.describe()}",
            )


# --- server side --------------------------------------------------------------------------------


class _Throttle:
    """Log a repeated event at most once per LOG_EVERY_S per key (bounded memory)."""

    def __init__(self, limit: int = 1024) -> None:
        self._last: dict[object, float] = {}
        self._limit = limit

    def due(self, key: object) -> bool:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < LOG_EVERY_S:
            return False
        if len(self._last) >= self._limit:
            self._last.clear()
        self._last[key] = now
        return True


class _AllowListAuthenticator(ThreadAuthenticator):
    """ZAP handler: admits the allow-listed CURVE keys, names the connection after the key's
    file (the ZAP User-Id), and logs refused keys with the peer address."""

    def __init__(
        self, context: zmq.Context, allowed: dict[bytes, KeyBinding], allowed_dir: Path
    ) -> None:
        super().__init__(context, log=logging.getLogger(f"{__name__}.zap"))
        self.allowed = allowed
        self.allowed_dir = allowed_dir
        self._address = "?"
        self._throttle = _Throttle()
        self.refused = 0
        self.configure_curve_callback("*", self)

    async def handle_zap_message(self, msg: list[bytes]) -> None:
        # The key check below sees only the key; keep the peer address for its log line.
        # (ZAP requests are handled one at a time, on the authenticator's own thread.)
        self._address = msg[3].decode("utf-8", "replace") if len(msg) > 3 else "?"
        await super().handle_zap_message(msg)

    def callback(self, domain: str, key: bytes) -> bool:
        """pyzmq's credentials-provider hook: is this z85 public key allowed?"""
        if key in self.allowed:
            return True
        self.refused += 1
        logger.log(
            logging.WARNING if self._throttle.due(key) else logging.DEBUG,
            "refused CURVE key %s from %s: not in the allow-list %s",
            key.decode("ascii", "replace"),
            self._address or "?",
            self.allowed_dir,
        )
        return False

    def curve_user_id(self, client_public_key: bytes) -> str:
        return self.allowed[z85.encode(client_public_key)].user_id()


def _protocol_error(value: int, *, curve: bool) -> str:
    if value == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH:
        if curve:
            return "security mechanism mismatch: a peer without CURVE (a plaintext agent?)"
        return "security mechanism mismatch: a peer using CURVE, and this server runs without it"
    if value == zmq.PROTOCOL_ERROR_ZMTP_CRYPTOGRAPHIC:
        return "cryptographic error: a peer using the wrong server public key?"
    return f"ZMTP protocol error {value:#x}"


def handshake_failure_logger(*, curve: bool) -> Callable[[int], None]:
    """What to do with a failed handshake on the server socket (a refused key is logged by the
    ZAP handler): a warning naming the likely cause, at most once a minute per cause."""
    throttle = _Throttle()

    def log(value: int) -> None:
        level = logging.WARNING if throttle.due(value) else logging.DEBUG
        logger.log(level, "refused a connection: %s", _protocol_error(value, curve=curve))

    return log


class ServerGuard:
    """What :func:`secure_server_socket` started; :meth:`stop` ends it (idempotent)."""

    def __init__(self, authenticator: _AllowListAuthenticator | None) -> None:
        self.authenticator = authenticator
        self._stopped = False
        # A failed bind between setup and the caller's try/finally must not leave threads.
        atexit.register(self.stop)

    def stop(self) -> None:
        if self._stopped:
            return
        self._stopped = True
        atexit.unregister(self.stop)
        if self.authenticator is not None:
            self.authenticator.stop()


def secure_server_socket(
    socket: zmq.Socket, context: zmq.Context, security: SecurityConfig
) -> ServerGuard:
    """Make the ROUTER a CURVE server guarded by the allow-list (when ``security.curve``).
    Failed handshakes are reported to :func:`handshake_failure_logger` by the server's
    connection guard (one socket monitor for all). Call before ``bind``: libzmq admits every
    CURVE client while no ZAP handler is running (its fail-closed option, ZAP_ENFORCE_DOMAIN,
    is a draft API; setting it on this non-draft build turned ZAP off altogether). Call
    :meth:`ServerGuard.stop` on the way out, before closing the socket and terminating the
    context."""
    authenticator = None
    if security.curve:
        keys = server_keys(security)  # first: a bad key file must not leave a thread behind
        authenticator = _AllowListAuthenticator(context, keys.allowed, keys.allowed_dir)
        authenticator.start()
        socket.curve_secretkey = keys.own.secret
        socket.curve_publickey = keys.own.public
        socket.curve_server = True
        logger.info(
            "CURVE on: %d allowed agent keys from %s (%s)",
            len(keys.allowed),
            keys.allowed_dir,
            ", ".join(sorted(b.name for b in keys.allowed.values())),
        )
    return ServerGuard(authenticator)


def _monitor(socket: zmq.Socket, events: int) -> zmq.Socket:
    address = f"inproc://fedhpg-monitor-{id(socket):x}-{os.getpid()}"
    socket.monitor(address, events)
    monitor = socket.context.socket(zmq.PAIR)
    monitor.setsockopt(zmq.LINGER, 0)
    monitor.connect(address)
    return monitor


def _user_id(frame: object) -> str | None:
    """The ZAP User-Id of the connection a message came on, or None without CURVE. ``frame``
    is any frame of the message, received with ``copy=False``."""
    get = getattr(frame, "get", None)
    if get is None:
        return None
    try:
        user_id = get("User-Id")
    except zmq.ZMQError:  # no such property: the connection was not authenticated by ZAP
        return None
    return str(user_id) or None


def authenticated_binding(frame: object) -> KeyBinding | None:
    """Who the CURVE key a message came with speaks for, or None without CURVE."""
    user_id = _user_id(frame)
    return KeyBinding.from_user_id(user_id) if user_id is not None else None


def authenticated_name(frame: object) -> str | None:
    """The id bound to the CURVE key a message came with, or None without CURVE."""
    binding = authenticated_binding(frame)
    return binding.name if binding is not None else None


def _peer_address(frame: object) -> str:
    try:
        return str(frame.get("Peer-Address"))  # type: ignore[attr-defined]
    except (AttributeError, zmq.ZMQError):
        return "?"


def key_mismatch(frame: object, agent_id: str | None, agents: range | None) -> str | None:
    """Why a message claiming to be ``agent_id`` speaking for ``agents`` must be refused, or
    None: with CURVE, a key speaks only as the id its allow-list entry names and for exactly
    the agents it names (a lone agent's key for its index, a host's for its whole range)."""
    user_id = _user_id(frame)
    if agent_id is None or agents is None or user_id is None:
        return None
    binding = KeyBinding.from_user_id(user_id)  # None only for a foreign User-Id: refused
    claimed = KeyBinding(agent_id, agents)
    if binding == claimed:
        return None
    held = binding.describe() if binding is not None else repr(user_id)
    return (
        f"the CURVE key of {held} (from {_peer_address(frame)}) cannot act as "
        f"{claimed.describe()}; a key speaks only for the agents its allow-list entry names"
    )


# --- agent side ---------------------------------------------------------------------------------


class HandshakeWatch:
    """Reads the agent socket's handshake events: :meth:`failure` says why the server refused us.

    Without it a refused handshake looks like silence and the agent would wait for
    ``agent.connect_timeout_s``, or longer: after a refusal at the protocol level (a refused
    key, a mechanism mismatch) libzmq drops the DEALER's only connection for good, and a
    blocking send then waits forever. So call :meth:`failure` before each send while
    registering. :meth:`close` before closing the socket (its monitor socket would otherwise
    block ``context.term()``).
    """

    EVENTS = (
        zmq.EVENT_HANDSHAKE_SUCCEEDED
        | zmq.EVENT_HANDSHAKE_FAILED_AUTH
        | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
        | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    )

    def __init__(self, socket: zmq.Socket, *, curve: bool, public_key: bytes | None) -> None:
        self.socket = socket
        self.curve = curve
        self.public_key = public_key
        self.monitor: zmq.Socket | None = _monitor(socket, self.EVENTS)
        self._no_detail = 0

    def failure(self) -> str | None:
        """Why the handshake was refused (one line), or None; reads pending events, never waits."""
        while self.monitor is not None and self.monitor.poll(0):
            event = recv_monitor_message(self.monitor, zmq.NOBLOCK)
            kind, value = event["event"], int(event["value"])
            if kind == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self._no_detail = 0
            elif kind == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
                return self._refused_key(value)
            elif kind == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
                return self._protocol(value)
            elif kind == zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL:
                self._no_detail += 1
                if self._no_detail >= NO_DETAIL_FAILURES:
                    return self._no_detail_message()
        return None

    def _refused_key(self, status: int) -> str:
        key = self.public_key.decode("ascii") if self.public_key else "?"
        if status == 400:
            return (
                f"the server refused this agent's CURVE key (not in its allow-list): public "
                f"key {key}"
            )
        return f"the server's authentication failed (ZAP status {status}) for public key {key}"

    def _protocol(self, value: int) -> str:
        if value == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH:
            if self.curve:
                return (
                    "the server does not use CURVE (security mechanism mismatch): start it with "
                    "security.curve=true, or run this agent without"
                )
            return (
                "the server requires CURVE encryption (security mechanism mismatch): run this "
                "agent with security.curve=true and its keys (security.keys_dir)"
            )
        return f"the handshake with the server failed (ZMTP protocol error {value:#x})"

    def _no_detail_message(self) -> str:
        # The server drops the connection before saying why when it sees the other mechanism
        # first (a race with our own check) or cannot decrypt our hello (a wrong server key).
        if self.curve:
            return (
                f"the CURVE handshake with the server failed {self._no_detail} times without a "
                "reason: security.server_public_key is not this server's key (server.key), or "
                "the server runs without CURVE"
            )
        return (
            f"the handshake with the server failed {self._no_detail} times without a reason: "
            "the server requires CURVE (run this agent with security.curve=true and its "
            "keys), or what listens there is no fedhpg server (check server.host and "
            "server.port)"
        )

    def close(self) -> None:
        if self.monitor is None:
            return
        if not self.socket.closed:
            self.socket.disable_monitor()
        self.monitor.close(linger=0)
        self.monitor = None


def secure_agent_socket(
    socket: zmq.Socket, security: SecurityConfig, agent_id: str
) -> HandshakeWatch:
    """Make the DEALER a CURVE client with ``agent_id``'s keys (when ``security.curve``), and
    watch its handshakes either way (a plaintext agent hears that the server wants CURVE).
    Call before ``connect``."""
    public = None
    if security.curve:
        keys = agent_keys(security, agent_id)
        socket.curve_secretkey = keys.own.secret
        socket.curve_publickey = keys.own.public
        socket.curve_serverkey = keys.server_public
        public = keys.own.public
    return HandshakeWatch(socket, curve=security.curve, public_key=public)
