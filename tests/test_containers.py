"""docker-compose.yml for real, under a Docker engine: the image built here (a Debian base made
with debootstrap and the wheels of this machine's pip configuration, no network in the build),
the federation of one server and four agent containers run to the end, crashes of an agent's and
of the server's process, and CURVE with read-only keys. Each run's final θ̃, read from the
results volume, must equal ``fedhpg-run``'s on loopback with the same seed and config.

Runs with ``make test-containers`` (FEDHPG_CONTAINER_TESTS=1); ``docker/engine.sh`` installs and
starts an engine where none answers and the machine allows it (root, Debian's packages
reachable), else the module is skipped with its reason. Everything the module starts is removed
by id: containers, networks and volumes of its compose projects, and the engine if it started
it. Images stay in the engine's store (a cache: ``make clean-containers`` removes it).

FEDHPG_CONTAINER_ROUNDS sets the rounds of every run (default 10); FEDHPG_CONTAINER_TIMINGS=FILE
writes the phases' wall times there as JSON (``make bench-containers``)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch
from procs import free_port, processes, start, wait_until

from fedhpg.server.checkpoint import latest_valid_checkpoint

ROOT = Path(__file__).parents[1]
ENGINE = ROOT / "docker" / "engine.sh"
IMAGE = "fedhpg:test"
BASE = "fedhpg-base:bookworm"
ROUNDS = int(os.environ.get("FEDHPG_CONTAINER_ROUNDS", "10"))
SEED = 3
TIMINGS: dict[str, float] = {}

pytestmark = [
    pytest.mark.skipif(
        os.environ.get("FEDHPG_CONTAINER_TESTS") != "1",
        reason="containers are tested by make test-containers (FEDHPG_CONTAINER_TESTS=1)",
    ),
    pytest.mark.timeout(1800),
]


@dataclass
class Engine:
    env: dict[str, str]

    def docker(self, *args: str, timeout: float = 120, check: bool = True) -> str:
        result = subprocess.run(
            ["docker", *args], env=self.env, capture_output=True, text=True, timeout=timeout
        )
        if check and result.returncode != 0:
            raise AssertionError(f"docker {' '.join(args)}: {result.stderr.strip()[-2000:]}")
        return result.stdout.strip()


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    result = subprocess.run(
        ["bash", str(ENGINE), "start"], capture_output=True, text=True, timeout=1200
    )
    if result.returncode == 3:
        pytest.skip(result.stderr.strip().splitlines()[-1])
    assert result.returncode == 0, result.stderr
    values = dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)
    env = {**os.environ, "DOCKER_HOST": values["DOCKER_HOST"], "COMPOSE_INTERACTIVE_NO_CLI": "1"}
    try:
        yield Engine(env)
    finally:
        if "STARTED" in values:
            subprocess.run(["bash", str(ENGINE), "stop"], timeout=120, check=True)
            pid = int(values["STARTED"])
            assert not Path(f"/proc/{pid}").exists(), "the engine this module started still runs"
        timings = os.environ.get("FEDHPG_CONTAINER_TIMINGS")
        if timings:
            Path(timings).write_text(json.dumps({"rounds": ROUNDS, **TIMINGS}, indent=2) + "\n")


def _timed(name: str, command: list[str], env: dict[str, str], timeout: float) -> None:
    begin = time.monotonic()
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{' '.join(command)}: {result.stderr.strip()[-2000:]}"
    TIMINGS[name] = round(time.monotonic() - begin, 1)


@pytest.fixture(scope="module")
def image(engine: Engine) -> str:
    """The base and the image, made here; an older build of the tag is removed once replaced."""
    if os.environ.get("FEDHPG_CONTAINER_COLD") == "1":  # timings from nothing
        for tag in (IMAGE, BASE):
            engine.docker("image", "rm", "-f", tag, check=False)
        engine.docker("builder", "prune", "-af", check=False)
    old = engine.docker("image", "inspect", "-f", "{{.Id}}", IMAGE, check=False)
    _timed("base_build_s", ["bash", str(ROOT / "docker" / "make-base.sh"), BASE], engine.env, 1200)
    _timed(
        "wheelhouse_s",
        ["bash", str(ROOT / "docker" / "make-wheelhouse.sh"), sys.executable],
        engine.env,
        900,
    )
    build = ["docker", "build", "--network", "none", "-q", "-t", IMAGE, str(ROOT)]
    args = ["--build-arg", f"BASE_IMAGE={BASE}", "--build-arg", "PIP_SOURCE=wheelhouse"]
    _timed("image_build_s", [*build[:2], *args, *build[2:]], engine.env, 1800)
    new = engine.docker("image", "inspect", "-f", "{{.Id}}", IMAGE)
    if old and old != new:
        engine.docker("image", "rm", old, check=False)
    TIMINGS["image_mb"] = round(
        int(engine.docker("image", "inspect", "-f", "{{.Size}}", IMAGE)) / 1e6
    )
    user = engine.docker(
        "run",
        "--pull",
        "never",
        "--rm",
        "--network",
        "none",
        IMAGE,
        "sh",
        "-c",
        "id -u; command -v gcc cc || true",
    )
    assert user.splitlines() == ["1000"], (
        f"the image must run as uid 1000 and hold no compiler: {user}"
    )
    return IMAGE


@dataclass
class Federation:
    """One compose project in its own directory (copies of the compose files, keys), removed
    by id whatever happens."""

    engine: Engine
    directory: Path
    files: list[str]
    project: str = field(default_factory=lambda: f"fedhpgtest{uuid.uuid4().hex[:8]}")

    def compose(self, *args: str, timeout: float = 300) -> str:
        command = ["docker-compose", "-p", self.project]
        for name in self.files:
            command += ["-f", name]
        env = {**self.engine.env, "FEDHPG_IMAGE": IMAGE, "FEDHPG_SEED": str(SEED)}
        env["FEDHPG_ROUNDS"] = str(ROUNDS)
        result = subprocess.run(
            [*command, *args],
            cwd=self.directory,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        assert result.returncode == 0, f"docker-compose {' '.join(args)}: {result.stderr[-3000:]}"
        return result.stdout.strip()

    def container(self, service: str) -> str:
        return self.compose("ps", "-q", service)

    def rounds_done(self) -> int:
        count = self.engine.docker(
            "exec",
            self.container("server"),
            "sh",
            "-c",
            "cat /runs/compose/metrics.jsonl 2>/dev/null | wc -l",
            check=False,
        )
        return int(count) if count.isdigit() else 0

    def wait(self, service: str, timeout: float) -> int:
        return int(self.engine.docker("wait", self.container(service), timeout=timeout))

    def restarts(self, service: str) -> int:
        return int(
            self.engine.docker("inspect", "-f", "{{.RestartCount}}", self.container(service))
        )

    def crash(self, service: str) -> None:
        """SIGKILL the service's fedhpg process from the host, as a crash would (docker kill
        is a manual stop, which `restart: on-failure` ignores). Its parent is the init."""
        init = int(self.engine.docker("inspect", "-f", "{{.State.Pid}}", self.container(service)))
        children = [
            int(pid)
            for task in Path(f"/proc/{init}/task").iterdir()
            for pid in (task / "children").read_text().split()
        ]
        assert children, f"{service}: no process under the container's init"
        for pid in children:
            os.kill(pid, signal.SIGKILL)

    def results(self, into: Path) -> Path:
        self.engine.docker("cp", f"{self.container('server')}:/runs/compose", str(into))
        return into

    def logs(self) -> str:
        return self.compose("logs", "--no-color", "--tail", "40")

    def remove(self) -> None:
        label = f"label=com.docker.compose.project={self.project}"
        for kind, listing in (
            ("container", ["ps", "-aq", "--filter", label]),
            ("network", ["network", "ls", "-q", "--filter", label]),
            ("volume", ["volume", "ls", "-q", "--filter", label]),
        ):
            ids = self.engine.docker(*listing).split()
            if ids:
                extra = ["-f", "-v"] if kind == "container" else []
                self.engine.docker(kind, "rm", *extra, *ids)
            assert not self.engine.docker(*listing), f"{kind}s of {self.project} left behind"


@pytest.fixture
def federation(engine: Engine, image: str, tmp_path: Path) -> Iterator[Federation]:
    for name in ("docker-compose.yml", "docker-compose.keys.yml"):
        shutil.copy(ROOT / name, tmp_path / name)
    made = Federation(engine, tmp_path, ["docker-compose.yml"])
    try:
        yield made
    finally:
        made.remove()


def _theta(run_dir: Path) -> torch.Tensor:
    checkpoint = latest_valid_checkpoint(run_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == ROUNDS, run_dir
    return checkpoint.theta


@pytest.fixture(scope="module")
def loopback_theta(tmp_path_factory: pytest.TempPathFactory) -> torch.Tensor:
    """The same federation through ``fedhpg-run`` on loopback (processes, not containers)."""
    directory = tmp_path_factory.mktemp("loopback")
    args = [
        "agents=demo4",
        f"rounds={ROUNDS}",
        f"seed={SEED}",
        f"server.port={free_port()}",
        f"server.out_dir={directory / 'run'}",
        f"hydra.run.dir={directory / 'hydra'}",
    ]
    begin = time.monotonic()
    with processes() as started:
        run = start(started, "fedhpg-run", args, cwd=directory)
        _, stderr = run.communicate(timeout=600)
    assert run.returncode == 0, stderr[-2000:]
    TIMINGS["loopback_run_s"] = round(time.monotonic() - begin, 1)
    return _theta(directory / "run")


def _run_to_end(federation: Federation, timeout: float = 600) -> Path:
    status = federation.wait("server", timeout)
    assert status == 0, f"server exit {status}\n{federation.logs()}"
    for k in range(4):
        assert federation.wait(f"agent-{k}", 60) == 0, federation.logs()
    return federation.results(federation.directory / "results")


def test_compose_federation_equals_loopback(
    federation: Federation, loopback_theta: torch.Tensor
) -> None:
    begin = time.monotonic()
    federation.compose("up", "-d", "--no-build")
    assert wait_until(lambda: federation.rounds_done() >= 1, 300, 0.2), federation.logs()
    TIMINGS["compose_up_to_round_1_s"] = round(time.monotonic() - begin, 1)
    results = _run_to_end(federation)
    TIMINGS["compose_run_s"] = round(time.monotonic() - begin, 1)
    assert torch.equal(_theta(results), loopback_theta)
    network = json.loads(
        federation.engine.docker("network", "inspect", f"{federation.project}_federation")
    )
    assert network[0]["Internal"] is True, "the federation's network must have no route out"


def test_traffic_stays_on_the_internal_network(federation: Federation) -> None:
    """Service names resolve on the federation's network, and nothing beyond its subnet is
    reachable: a listener on a second network (made by this test, so no packet is sent to a
    host it did not create) answers its own network's containers and not the federation's."""
    federation.compose("up", "-d", "--no-build", "server")
    docker = federation.engine.docker
    label = f"com.docker.compose.project={federation.project}"  # removed with the project
    outside = f"{federation.project}_outside"
    docker("network", "create", "--label", label, outside)
    listen = (
        "import socket; s = socket.create_server(('0.0.0.0', 9000)); [s.accept() for _ in range(9)]"
    )
    listener = docker(
        "run",
        "--pull",
        "never",
        "-d",
        "--label",
        label,
        "--network",
        outside,
        IMAGE,
        "python",
        "-c",
        listen,
    )
    address = docker(
        "inspect",
        "-f",
        f'{{{{(index .NetworkSettings.Networks "{outside}").IPAddress}}}}',
        listener,
    )
    probe = (
        "import socket, sys\n"
        "print(socket.gethostbyname(sys.argv[1]))\n"
        "try:\n"
        "    socket.create_connection((sys.argv[2], 9000), 3).close()\n"
        "    print('reached')\n"
        "except OSError as error:\n"
        "    print(type(error).__name__)\n"
    )

    def from_network(network: str, name: str) -> list[str]:
        return docker(
            "run",
            "--pull",
            "never",
            "--rm",
            "--network",
            network,
            IMAGE,
            "python",
            "-c",
            probe,
            name,
            address,
        ).splitlines()

    inside = from_network(f"{federation.project}_federation", "server")
    assert inside[1] != "reached", f"a federation container reached {address} on another network"
    assert inside[0].count(".") == 3  # the server's name resolved
    assert from_network(outside, listener[:12])[1] == "reached"  # the listener does answer
    network = json.loads(docker("network", "inspect", f"{federation.project}_federation"))
    assert network[0]["Internal"] is True


def test_crashed_agent_container_restarts_and_rejoins(
    federation: Federation, loopback_theta: torch.Tensor
) -> None:
    federation.compose("up", "-d", "--no-build")
    assert wait_until(lambda: federation.rounds_done() >= 2, 300, 0.2), federation.logs()
    federation.crash("agent-1")
    results = _run_to_end(federation)
    assert federation.restarts("agent-1") == 1
    summary = json.loads((results / "summary.json").read_text())
    assert summary["agent_deaths"] == 1 and summary["agent_rejoins"] == 1, summary
    assert torch.equal(_theta(results), loopback_theta)


def test_crashed_server_container_resumes(
    federation: Federation, loopback_theta: torch.Tensor
) -> None:
    federation.compose("up", "-d", "--no-build")
    assert wait_until(lambda: federation.rounds_done() >= 3, 300, 0.2), federation.logs()
    federation.crash("server")
    results = _run_to_end(federation)
    assert federation.restarts("server") == 1
    assert "resuming /runs/compose after round" in federation.compose(
        "logs", "--no-color", "server"
    )
    assert torch.equal(_theta(results), loopback_theta)


def test_curve_federation_with_read_only_keys(
    federation: Federation, loopback_theta: torch.Tensor
) -> None:
    keys = federation.directory / "keys"
    made = subprocess.run(
        [str(Path(sys.executable).parent / "fedhpg-keys"), str(keys), "--agents", "4"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert made.returncode == 0, made.stderr
    for path in [keys, *keys.rglob("*")]:
        os.chown(path, 1000, 1000)  # the image's user reads them
    federation.files.append("docker-compose.keys.yml")
    federation.compose("up", "-d", "--no-build")
    results = _run_to_end(federation)
    assert torch.equal(_theta(results), loopback_theta)
    mounts = json.loads(
        federation.engine.docker(
            "inspect", "-f", "{{json .Mounts}}", federation.container("agent-0")
        )
    )
    keyed = [m for m in mounts if m["Destination"].startswith("/keys/")]
    assert len(keyed) == 2 and not any(m["RW"] for m in keyed), keyed
    assert json.loads((results / "config.json").read_text())["security"]["curve"] is True
