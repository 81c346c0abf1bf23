"""CURVE encryption and key-based agent authentication, with real processes on loopback and keys
made by the real ``fedhpg-keys``: allowed keys register and finish a run; an unknown key, a
plaintext agent and a key given to another agent id are refused quickly, in one clear line, and
logged by the server, which keeps serving. Also ``fedhpg-keys`` itself and the config checks."""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import msgpack
import pytest
import yaml
import zmq
import zmq.auth
from procs import BIN, free_port, processes, start

from fedhpg.common.configuration.config import RunConfig, from_dict, to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.run_roles import adopt_settings, dictated_settings
from fedhpg.common.runtime.cli import compose, validate_config
from fedhpg.common.wire.codec import decode
from fedhpg.common.wire.protocol import PROTOCOL_VERSION, Error
from fedhpg.common.wire.security import (
    KEY_MISMATCH,
    KeyBinding,
    SecurityConfig,
    authenticated_name,
    key_mismatch,
    load_allow_list,
    parse_binding,
    secure_server_socket,
)

TIMEOUT_S = 120
ROOT = Path(__file__).parents[1]
REFUSAL_BOUND_S = 30.0
"""An agent refused at the handshake must give up well before its connect timeout (60 s)."""


@pytest.fixture
def started() -> Iterator[list[subprocess.Popen]]:
    """Processes a test starts; every one still running is killed, pass or fail."""
    with processes() as procs:
        yield procs


def _keys(tmp_path: Path, name: str, *args: str) -> Path:
    directory = tmp_path / name
    result = subprocess.run(
        [str(BIN / "fedhpg-keys"), str(directory), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    return directory


def _overrides(port: int, out_dir: Path, *, agents: int = 2, rounds: int = 3) -> list[str]:
    return [
        f"rounds={rounds}",
        f"agents.num_agents={agents}",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        f"eval.every={rounds}",
        "eval.episodes=3",
        f"server.port={port}",
        f"server.out_dir={out_dir}",
    ]


def _curve(keys: Path) -> list[str]:
    return ["security.curve=true", f"security.keys_dir={keys}"]


def _lent_keys(keys: Path, secret: Path) -> list[str]:
    """An agent holding ``secret`` instead of its own key (and the right server key)."""
    return [
        "security.curve=true",
        f"security.agent_secret_key={secret}",
        f"security.server_public_key={keys / 'server.key'}",
    ]


def _refused(started: list, args: list[str], cwd: Path) -> tuple[str, float]:
    """Run an agent that must be refused: its stderr, and how long it took to give up."""
    begin = time.monotonic()
    agent = start(started, "fedhpg-agent", [*args, "agent.connect_timeout_s=60"], cwd=cwd)
    _, stderr = agent.communicate(timeout=TIMEOUT_S)
    elapsed = time.monotonic() - begin
    assert agent.returncode == 1, stderr
    assert "Traceback" not in stderr
    return stderr, elapsed


def _finish(server: subprocess.Popen, agents: list[subprocess.Popen]) -> str:
    _, stderr = server.communicate(timeout=TIMEOUT_S)
    for agent in agents:
        agent.wait(timeout=30)
    assert server.returncode == 0, stderr[-3000:]
    assert [a.returncode for a in agents] == [0] * len(agents)
    return stderr


def _metrics_rounds(out_dir: Path) -> int:
    return len((out_dir / "metrics.jsonl").read_text().splitlines())


def _curve_dealer(context: zmq.Context, port: int, secret: Path, server_key: Path) -> zmq.Socket:
    public, secret_key = zmq.auth.load_certificate(secret)
    socket = context.socket(zmq.DEALER)
    socket.setsockopt(zmq.LINGER, 0)
    socket.curve_publickey, socket.curve_secretkey = public, secret_key
    socket.curve_serverkey = zmq.auth.load_certificate(server_key)[0]
    socket.connect(f"tcp://127.0.0.1:{port}")
    return socket


def _heartbeat(*extra: bytes) -> list[bytes]:
    return [
        msgpack.packb({"v": PROTOCOL_VERSION, "type": "heartbeat", "fields": {}, "arrays": []}),
        *extra,
    ]


# --- with the right keys ----------------------------------------------------------------------


@pytest.mark.timeout(TIMEOUT_S + 60)
def test_curve_federation_with_allowed_keys_completes(tmp_path: Path, started: list) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "2")
    port, out_dir = free_port(), tmp_path / "run"
    overrides = [*_overrides(port, out_dir), *_curve(keys)]
    server = start(started, "fedhpg-server", overrides, cwd=tmp_path)
    context = zmq.Context()
    try:
        # The size cap holds inside CURVE too: an allowed key's oversized message is dropped
        # (no reply), while a small one from the same key is answered.
        big = _curve_dealer(context, port, keys / "agent-1.key_secret", keys / "server.key")
        big.send_multipart(_heartbeat(b"\x00" * (2 << 20)))
        assert not big.poll(2000)
        big.close()
        small = _curve_dealer(context, port, keys / "agent-1.key_secret", keys / "server.key")
        small.send_multipart(_heartbeat())
        assert small.poll(20_000), "the server did not answer an allowed key"
        reply = decode(small.recv_multipart())
        assert isinstance(reply, Error) and reply.code == "not_registered"
        small.close()
    finally:
        context.term()
    agents = [
        start(started, "fedhpg-agent", [*overrides, f"agent.index={k}"], cwd=tmp_path)
        for k in range(2)
    ]
    stderr = _finish(server, agents)
    assert "refused" not in stderr
    assert _metrics_rounds(out_dir) == 3


@pytest.mark.timeout(TIMEOUT_S)
def test_launcher_runs_a_curve_federation(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "2")
    out_dir = tmp_path / "run"
    result = subprocess.run(
        [
            str(BIN / "fedhpg-run"),
            *_overrides(0, out_dir),
            *_curve(keys),
            f"hydra.run.dir={tmp_path / 'hydra'}",
        ],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S - 10,
        cwd=tmp_path,
        env={**os.environ, "FEDHPG_LOG_LEVEL": "INFO"},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "CURVE on: 2 allowed agent keys" in result.stdout + result.stderr  # Hydra's logging
    assert _metrics_rounds(out_dir) == 3


def test_launcher_checks_every_agent_key_before_starting(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "2")
    (keys / "agent-1.key_secret").unlink()
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), *_overrides(0, tmp_path / "run", agents=2), *_curve(keys)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: security.keys_dir: {keys / 'agent-1.key_secret'}: no such key file "
        "(generate keys with fedhpg-keys)"
    ]


# --- refusals ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Refusal:
    """A refused agent's stderr and how long it took to give up."""

    stderr: str
    elapsed: float


@dataclass(frozen=True)
class RefusedAtOneServer:
    """One CURVE federation of two agents (both keys allowed) whose server first meets, one
    after another, every agent it must refuse, then runs to its end with the two honest agents:
    the refusals' outcomes, the server's stderr and the rounds it wrote."""

    refused: dict[str, Refusal]
    stranger_key: str
    server_err: str
    rounds: int


REFUSED_AGENTS = ("unknown key", "plaintext agent", "lent key", "lone agent's key")
SHARED_TIMEOUT_S = TIMEOUT_S + 60 + len(REFUSED_AGENTS) * REFUSAL_BOUND_S
"""The refusals' tests: the first to run builds their shared federation, four refusals and a
run (each test's own bound was TIMEOUT_S + 60, a refusal's REFUSAL_BOUND_S)."""


@pytest.fixture(scope="module")
def refused_at_one_server(tmp_path_factory: pytest.TempPathFactory) -> RefusedAtOneServer:
    """The refusals a CURVE server makes, each as its own test once made a federation of its
    own (a server, the refused agent, the honest agents, 3 rounds): here they share one, which
    keeps serving after each and completes the run, which is what each test asserts besides
    its refusal. ``server.register_timeout_s`` covers the refusals one after another, each
    bounded by REFUSAL_BOUND_S."""
    tmp_path = tmp_path_factory.mktemp("refusals")
    keys = _keys(tmp_path, "keys", "--agents", "2")
    strangers = _keys(tmp_path, "strangers", "--agents", "1")  # valid pairs, never allowed
    port, out_dir = free_port(), tmp_path / "run"
    overrides = [
        *_overrides(port, out_dir, agents=2),
        f"server.register_timeout_s={len(REFUSED_AGENTS) * REFUSAL_BOUND_S + 60:g}",
    ]
    secret = strangers / "agent-0.key_secret"
    attempts = {
        "unknown key": [*overrides, *_lent_keys(keys, secret)],
        "plaintext agent": overrides,
        # agent-1's key (allowed) presented under agent-0's id
        "lent key": [*overrides, "agent.index=0", *_lent_keys(keys, keys / "agent-1.key_secret")],
        # agent-0's key, under agent-0's own id, claiming index 1
        "lone agent's key": [*overrides, *_curve(keys), "agent.index=1", "agent.id=agent-0"],
    }
    assert tuple(attempts) == REFUSED_AGENTS
    with processes() as started:
        server = start(started, "fedhpg-server", [*overrides, *_curve(keys)], cwd=tmp_path)
        refused = {}
        for name, args in attempts.items():
            stderr, elapsed = _refused(started, args, tmp_path)
            refused[name] = Refusal(stderr, elapsed)
        agents = [
            start(
                started,
                "fedhpg-agent",
                [*overrides, *_curve(keys), f"agent.index={k}"],
                cwd=tmp_path,
            )
            for k in range(2)
        ]
        server_err = _finish(server, agents)
    return RefusedAtOneServer(
        refused,
        zmq.auth.load_certificate(secret)[0].decode(),
        server_err,
        _metrics_rounds(out_dir),
    )


@pytest.mark.timeout(SHARED_TIMEOUT_S)
def test_unknown_key_cannot_register_and_is_logged(
    refused_at_one_server: RefusedAtOneServer,
) -> None:
    shared = refused_at_one_server
    refusal, stranger_key = shared.refused["unknown key"], shared.stranger_key
    assert "the server refused this agent's CURVE key (not in its allow-list)" in refusal.stderr
    assert stranger_key in refusal.stderr
    assert refusal.elapsed < REFUSAL_BOUND_S, (
        f"took {refusal.elapsed:.1f} s: waited for the connect timeout?"
    )

    # The server keeps serving: the allowed agents register and the run completes.
    assert f"refused CURVE key {stranger_key} from " in shared.server_err
    assert shared.rounds == 3


def _plaintext_and_curve_refusal(stderr: str, elapsed: float) -> None:
    assert elapsed < REFUSAL_BOUND_S, f"took {elapsed:.1f} s: waited for the connect timeout?"
    lines = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, stderr
    # Which side notices first is a race: the agent hears "mismatch" or, when the server hangs
    # up first, sees three failed handshakes; both lines name CURVE as the likely cause. (The
    # server logs the mismatch when it is the one to notice, so that is not asserted.)
    assert "CURVE" in lines[0] and ("mismatch" in lines[0] or "failed 3 times" in lines[0])


@pytest.mark.parametrize(
    "curve_side",
    [
        pytest.param("server", marks=pytest.mark.timeout(SHARED_TIMEOUT_S)),
        pytest.param("agent", marks=pytest.mark.timeout(TIMEOUT_S + 60)),
    ],
)
def test_plaintext_and_curve_do_not_mix(
    tmp_path: Path, started: list, curve_side: str, request: pytest.FixtureRequest
) -> None:
    if curve_side == "server":  # a plaintext agent, at the CURVE server the refusals share
        shared: RefusedAtOneServer = request.getfixturevalue("refused_at_one_server")
        refusal = shared.refused["plaintext agent"]
        _plaintext_and_curve_refusal(refusal.stderr, refusal.elapsed)
        # The server keeps serving: agents with its settings register and the run completes.
        assert shared.rounds == 3
        return
    keys = _keys(tmp_path, "keys", "--agents", "1")
    port, out_dir = free_port(), tmp_path / "run"
    server_args = _overrides(port, out_dir, agents=1)
    agent_args = [*server_args, *_curve(keys)]
    server = start(started, "fedhpg-server", server_args, cwd=tmp_path)
    _plaintext_and_curve_refusal(*_refused(started, agent_args, tmp_path))

    # The server keeps serving: an agent with its settings registers and the run completes.
    agent = start(started, "fedhpg-agent", server_args, cwd=tmp_path)
    _finish(server, [agent])
    assert _metrics_rounds(out_dir) == 3


@pytest.mark.timeout(SHARED_TIMEOUT_S)
def test_allowed_key_lent_to_another_agent_id_is_rejected(
    refused_at_one_server: RefusedAtOneServer,
) -> None:
    stderr = refused_at_one_server.refused["lent key"].stderr
    assert f"server refused registration ({KEY_MISMATCH})" in stderr
    assert "'agent-1'" in stderr and "'agent-0'" in stderr

    # agent-0 with its own key takes the place the impostor could not, and the run completes.
    assert f"{KEY_MISMATCH}: the CURVE key of 'agent-1'" in refused_at_one_server.server_err
    assert refused_at_one_server.rounds == 3


@pytest.mark.timeout(TIMEOUT_S + 60)
def test_a_hosts_key_cannot_register_another_range(tmp_path: Path, started: list) -> None:
    """The key of host-0-2 claiming agents 3..5 under its own name (it took them, and with 6
    of 9 agents the median, before): refused with key_mismatch before anything is registered;
    the real hosts then run the federation to its end."""
    keys = _keys(tmp_path, "keys", "--names", "host-0-2", "host-3-5")
    port, out_dir = free_port(), tmp_path / "run"
    overrides = [*_overrides(port, out_dir, agents=6), *_curve(keys)]
    server = start(started, "fedhpg-server", overrides, cwd=tmp_path)
    thief = [*overrides, "agent.first=3", "agent.count=3", "agent.id=host-0-2"]
    stderr, _ = _refused(started, thief, tmp_path)
    assert f"server refused registration ({KEY_MISMATCH})" in stderr
    assert "'host-0-2' (agents 0..2)" in stderr and "'host-0-2' (agents 3..5)" in stderr
    hosts = [
        start(
            started, "fedhpg-agent", [*overrides, f"agent.first={f}", "agent.count=3"], cwd=tmp_path
        )
        for f in (0, 3)
    ]
    server_err = _finish(server, hosts)
    assert f"{KEY_MISMATCH}: the CURVE key of 'host-0-2' (agents 0..2)" in server_err
    assert "duplicate_agent" not in server_err
    assert _metrics_rounds(out_dir) == 3


@pytest.mark.timeout(SHARED_TIMEOUT_S)
def test_a_lone_agents_key_cannot_register_another_index(
    refused_at_one_server: RefusedAtOneServer,
) -> None:
    """agent-0's key, under agent-0's own id, claiming index 1 (it took the index before, and
    the honest agent-1 was refused): refused; agent-1 then takes its place."""
    stderr = refused_at_one_server.refused["lone agent's key"].stderr
    assert f"server refused registration ({KEY_MISMATCH})" in stderr
    assert "'agent-0' (agent 0)" in stderr and "'agent-0' (agent 1)" in stderr
    assert refused_at_one_server.rounds == 3


class _Frame:
    """What key_mismatch reads of a received frame: its connection's properties."""

    def __init__(self, user_id: str | None) -> None:
        self.user_id = user_id

    def get(self, name: str) -> str:
        if name == "Peer-Address":
            return "127.0.0.1"
        if self.user_id is None:
            raise zmq.ZMQError(zmq.EINVAL)
        return self.user_id


@pytest.mark.parametrize(
    ("stem", "name", "agents"),
    [
        ("agent-3", "agent-3", range(3, 4)),
        ("host-0-2", "host-0-2", range(0, 3)),
        ("alice@5", "alice", range(5, 6)),
        ("rack.a@10-19", "rack.a", range(10, 20)),
        ("agent-3@7", "agent-3", range(7, 8)),
    ],
)
def test_an_allow_list_entry_names_exactly_its_agents(stem: str, name: str, agents: range) -> None:
    binding = parse_binding(stem)
    assert binding == KeyBinding(name, agents)
    assert KeyBinding.from_user_id(binding.user_id()) == binding
    frame = _Frame(binding.user_id())
    assert key_mismatch(frame, name, agents) is None
    assert key_mismatch(frame, name, range(agents.start, agents.stop + 1)) is not None  # wider
    assert key_mismatch(frame, name, range(agents.start + 1, agents.stop + 1)) is not None
    assert key_mismatch(frame, name + "x", agents) is not None
    assert key_mismatch(_Frame(None), "anyone", range(0, 9)) is None  # no CURVE: no key
    assert key_mismatch(_Frame("forged"), name, agents) is not None  # never fails open


def test_an_allow_list_entry_without_agents_is_refused_in_one_line(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--names", "alice@0")
    (keys / "allowed" / "alice@0.key").rename(keys / "allowed" / "alice.key")
    with pytest.raises(ConfigError, match=r"alice.key: names no agents: call it alice@<index>"):
        load_allow_list(keys / "allowed", "security.allowed_keys_dir")


def test_launcher_checks_each_hosts_key_is_bound_to_its_range(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "4", "--per-host", "2")
    allowed = keys / "allowed"
    (allowed / "host-2-3.key").rename(allowed / "host-2-3@2-2.key")
    result = subprocess.run(
        [
            str(BIN / "fedhpg-run"),
            *_overrides(0, tmp_path / "run", agents=4),
            *_curve(keys),
            "agents.per_host=2",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: security.allowed_keys_dir: {allowed}: host-2-3's public key is allowed as "
        "'host-2-3' (agent 2), not as 'host-2-3' (agents 2..3)"
    ]


# --- compose: docker-compose.keys.yml, run as its commands on loopback (no Docker engine here) --

COMPOSE_VARIABLE = re.compile(r"\$\{(\w+):-([^}]*)\}")
SECURITY_ARGS = ["security.curve=true", "security.keys_dir=/keys"]


def _compose_services(name: str) -> dict:
    return yaml.safe_load((ROOT / name).read_text())["services"]


def test_compose_keys_override_only_adds_keys() -> None:
    base, keyed = (
        _compose_services("docker-compose.yml"),
        _compose_services("docker-compose.keys.yml"),
    )
    assert set(keyed) == set(base)
    for name, service in keyed.items():
        assert service["command"] == [*base[name]["command"], *SECURITY_ARGS], name
        mounts = [volume.split(":") for volume in service["volumes"]]
        assert all(len(m) == 3 and m[2] == "ro" for m in mounts), f"{name}: read-only mounts"
        assert all(
            source == f"./keys/{target.removeprefix('/keys/')}" for source, target, _ in mounts
        )
        files = sorted(target.removeprefix("/keys/") for _, target, _ in mounts)
        if name == "server":
            assert files == ["allowed", "server.key_secret"]
        else:
            index = next(a for a in service["command"] if a.startswith("agent.index="))
            agent = f"agent-{index.split('=')[1]}"
            assert agent == name and files == [f"{agent}.key_secret", "server.key"], name


def _container(root: Path, keys: Path, service: dict) -> list[str]:
    """The files a container would see under /keys, copied into ``root``; its command there."""
    for volume in service["volumes"]:
        source, target, _ = volume.split(":")
        host, inside = keys / source.removeprefix("./keys/"), root / target.lstrip("/")
        inside.parent.mkdir(parents=True, exist_ok=True)
        if host.is_dir():
            shutil.copytree(host, inside)
        else:
            shutil.copy2(host, inside)
    return [arg.replace("=/keys", f"={root / 'keys'}") for arg in service["command"]]


@pytest.mark.slow
@pytest.mark.timeout(TIMEOUT_S + 60)
def test_compose_with_keys_runs_a_curve_federation(tmp_path: Path, started: list) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "4")
    env = {
        "FEDHPG_PORT": str(free_port()),
        "FEDHPG_BIND_ALL": "false",
        "FEDHPG_RUNS": str(tmp_path),
        "FEDHPG_ROUNDS": "2",
    }
    processes_by_name = {}
    for name, service in _compose_services("docker-compose.keys.yml").items():
        command = _container(tmp_path / "containers" / name, keys, service)
        args = [COMPOSE_VARIABLE.sub(lambda m: env.get(m[1], m[2]), a) for a in command[1:]]
        args = [a.replace("server.host=server", "server.host=127.0.0.1") for a in args]
        processes_by_name[name] = start(started, command[0], args, cwd=tmp_path)
    server = processes_by_name.pop("server")
    _finish(server, list(processes_by_name.values()))
    assert _metrics_rounds(tmp_path / "compose") == 2


# --- in-process: the key is bound to the agent name, and stop() leaves nothing behind ---------


def test_authenticated_name_is_the_allow_list_file_name(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--names", "alice@0", "bob@1")
    security = SecurityConfig(curve=True, keys_dir=str(keys))
    before = set(threading.enumerate())
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    guard = secure_server_socket(router, context, security)
    try:
        port = router.bind_to_random_port("tcp://127.0.0.1")
        dealer = _curve_dealer(context, port, keys / "bob.key_secret", keys / "server.key")
        dealer.send(b"hi")
        assert router.poll(10_000)
        frames = router.recv_multipart(copy=False)
        assert authenticated_name(frames[1]) == "bob"
        assert authenticated_name(b"plain bytes") is None
        dealer.close()
    finally:
        guard.stop()
        guard.stop()  # idempotent
        router.close()
    terminated = threading.Thread(target=context.term, daemon=True)
    terminated.start()
    terminated.join(10)
    assert not terminated.is_alive(), "context.term() hangs: a socket was left open"
    assert set(threading.enumerate()) - before == set(), "threads left running after stop()"


# --- fedhpg-keys ------------------------------------------------------------------------------


def test_keys_command_writes_pairs_and_the_allow_list(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "3")
    names = ["server", "agent-0", "agent-1", "agent-2"]
    for name in names:
        secret = keys / f"{name}.key_secret"
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600, name
        assert stat.S_IMODE((keys / f"{name}.key").stat().st_mode) == 0o644, name
        public, secret_key = zmq.auth.load_certificate(secret)
        assert secret_key is not None and zmq.curve_public(secret_key) == public
        assert zmq.auth.load_certificate(keys / f"{name}.key") == (public, None)
    allowed = sorted(p.name for p in (keys / "allowed").iterdir())
    assert allowed == ["agent-0.key", "agent-1.key", "agent-2.key"]
    for name in allowed:
        assert (keys / "allowed" / name).read_bytes() == (keys / name).read_bytes()
    assert sorted(p.name for p in keys.iterdir() if p.name.startswith(".")) == []


def test_keys_command_force_replaces_and_names_stale_entries(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "2")
    before = (keys / "server.key_secret").read_bytes()
    result = subprocess.run(
        [str(BIN / "fedhpg-keys"), str(keys), "--agents", "1", "--force"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert (keys / "server.key_secret").read_bytes() != before
    assert "still allows agent-1" in result.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--agents", "0"], "--agents: got 0"),
        (["--agents", "two"], "--agents: got 'two'"),
        (["--names", "bad/name"], "is not a valid agent id"),
        (["--names", "a@0", "a@1"], "given more than once: a"),
        (["--names", "alice"], "'alice' names no agents: call it alice@<index>"),
        (["--names", "alice@x"], "comes an agent index or a range FIRST-LAST, got 'x'"),
        (["--names", "rack@5-2"], "the range 5-2 is empty"),
        (["--agents", "4", "--per-host", "0"], "--per-host: got 0"),
        (["--names", "a@0", "--per-host", "2"], "--per-host: goes with --agents"),
        (["--names", "server"], "is the server's key name"),
        (["--agents", "2", "--names", "a"], "not allowed with argument"),
        (["--no-such-flag"], "unrecognized arguments"),
    ],
)
def test_keys_command_bad_input_is_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = subprocess.run(
        [str(BIN / "fedhpg-keys"), str(tmp_path / "keys"), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not (tmp_path / "keys").exists()


def test_keys_command_refuses_existing_keys_and_unwritable_places(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "1")
    secret = (keys / "agent-0.key_secret").read_bytes()
    (tmp_path / "a-file").write_text("")
    for target, message in [
        (keys, "already exists"),
        (tmp_path / "a-file" / "keys", "Not a directory"),
        (tmp_path / "a-file", "exists and is not a directory"),
    ]:
        result = subprocess.run(
            [str(BIN / "fedhpg-keys"), str(target), "--agents", "1"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert result.returncode == 2, target
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], result.stderr
    assert (keys / "agent-0.key_secret").read_bytes() == secret, "an existing key was replaced"


# --- configuration ----------------------------------------------------------------------------


def test_security_is_off_by_default_and_takes_overrides(tmp_path: Path) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "1")
    assert compose([]).security == SecurityConfig()
    run = compose(_curve(keys))
    assert run.security.curve and run.security.keys_dir == str(keys)


@pytest.mark.parametrize(
    ("overrides", "key", "message"),
    [
        (["security.curve=true"], "security.keys_dir", "no keys are given"),
        (["security.curve=true", "security.keys_dir=/nowhere"], "security.keys_dir", "no such"),
        (["security.curve=maybe"], "security.curve", ""),
        (["security.curve=true", "security.server_secret_key=KEYS/server.key"], None, "no secret"),
        (["security.curve=true", "security.server_public_key=KEYS/server.key_secret"], None, ""),
        (
            ["security.curve=true", "security.agent_secret_key=KEYS/nope.key_secret"],
            None,
            "no such",
        ),
        (["security.curve=true", "security.server_secret_key=NOTAKEY"], None, "not a CURVE key"),
        (
            ["security.curve=true", "security.allowed_keys_dir=KEYS/allowed"],
            None,
            "also allowed as 'agent-0' (agent 0)",
        ),
    ],
)
def test_bad_security_values_name_the_key(
    tmp_path: Path, overrides: list[str], key: str | None, message: str
) -> None:
    keys = _keys(tmp_path, "keys", "--agents", "1")
    (tmp_path / "not-a-key").write_text("public-key-ish = nothing\n")
    # A second name for agent-0's key: the allow-list is then ambiguous.
    (keys / "allowed" / "twin@1.key").write_bytes((keys / "agent-0.key").read_bytes())
    resolved = [
        o.replace("KEYS", str(keys)).replace("NOTAKEY", str(tmp_path / "not-a-key"))
        for o in overrides
    ]
    with pytest.raises(ConfigError) as info:
        compose(resolved)
    expected = key or resolved[-1].split("=", 1)[0]
    assert info.value.key == expected, str(info.value)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_agents_never_see_the_servers_key_paths() -> None:
    """The server sends agents only the keys it dictates (config.GROUPS): its key paths, which
    would fail on an agent's host and concern no agent, never leave it."""
    run = RunConfig(security=SecurityConfig(curve=True, keys_dir="/only/on/the/server"))
    with pytest.raises(ConfigError, match=r"security\.keys_dir"):
        validate_config(from_dict(to_dict(run)))
    dictated = dictated_settings(run)
    assert "security" not in dictated and "server" not in dictated
    agent = adopt_settings(RunConfig(seed=5), dictated)
    assert agent.security == SecurityConfig()
    assert agent.seed == run.seed and agent.algo == run.algo
