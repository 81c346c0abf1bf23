"""docker-compose.yml, tested without a Docker engine: its structure, and a federation made of
exactly its service commands, run here with the service host names resolved to loopback."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from procs import free_port, processes, start

COMPOSE = Path(__file__).parents[1] / "docker-compose.yml"
VARIABLE = re.compile(r"\$\{(\w+):-([^}]*)\}")


def _services() -> dict:
    return yaml.safe_load(COMPOSE.read_text())["services"]


def _interpolate(text: str, env: dict[str, str]) -> str:
    """Compose's ${NAME:-default}."""
    return VARIABLE.sub(lambda m: env.get(m.group(1), m.group(2)), text)


def _command(service: dict, env: dict[str, str], hosts: dict[str, str]) -> list[str]:
    args = [_interpolate(str(a), env) for a in service["command"]]
    resolved = []
    for arg in args:
        key, _, value = arg.partition("=")
        resolved.append(f"{key}={hosts[value]}" if key == "server.host" and value in hosts else arg)
    return resolved


def test_compose_structure() -> None:
    services = _services()
    agents = {name: s for name, s in services.items() if name.startswith("agent-")}
    assert len(agents) == 4
    indices = sorted(
        next(a for a in s["command"] if a.startswith("agent.index=")) for s in agents.values()
    )
    assert indices == [f"agent.index={k}" for k in range(4)]
    server = services["server"]
    assert "healthcheck" in server and server["volumes"]
    for agent in agents.values():
        assert agent["depends_on"]["server"]["condition"] == "service_healthy"
        assert agent["restart"].startswith("on-failure")
        assert "server.host=server" in agent["command"], "agents find the server by service name"


def _compose_client() -> list[str] | None:
    """The compose v2 plugin, else Debian's docker-compose 1.29 (docker/engine.sh installs it)."""
    if shutil.which("docker"):
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True)
        if probe.returncode == 0:
            return ["docker", "compose"]
    found = shutil.which("docker-compose")
    return [found] if found else None


def test_docker_compose_accepts_the_files() -> None:
    client = _compose_client()
    if client is None:
        pytest.skip("no compose client here (neither the docker compose plugin nor docker-compose)")
    for files in (
        ["docker-compose.yml"],
        ["docker-compose.yml", "docker-compose.keys.yml"],
        ["docker-compose.yml", "docker-compose.expose.yml"],
    ):
        args = [a for name in files for a in ("-f", str(COMPOSE.parent / name))]
        result = subprocess.run([*client, *args, "config", "-q"], capture_output=True, text=True)
        assert result.returncode == 0, f"{files}: {result.stderr}"


@pytest.mark.slow
def test_the_compose_commands_run_a_federation(tmp_path: Path) -> None:
    env = {
        "FEDHPG_PORT": str(free_port()),
        "FEDHPG_BIND_ALL": "false",  # tests bind loopback only; compose binds all interfaces
        "FEDHPG_RUNS": str(tmp_path),
        "FEDHPG_ROUNDS": "6",
    }
    hosts = {name: "127.0.0.1" for name in _services()}
    services = _services()
    with processes() as started:
        server = start(
            started, "fedhpg-server", _command(services["server"], env, hosts)[1:], cwd=tmp_path
        )
        agents = [
            start(started, s["command"][0], _command(s, env, hosts)[1:], cwd=tmp_path)
            for name, s in services.items()
            if name != "server"
        ]
        _, stderr = server.communicate(timeout=180)
        for agent in agents:
            agent.wait(timeout=30)
    assert server.returncode == 0, stderr[-2000:]
    assert [a.returncode for a in agents] == [0, 0, 0, 0]
    records = [
        json.loads(line)
        for line in (tmp_path / "compose" / "metrics.jsonl").read_text().splitlines()
    ]
    assert [r["round"] for r in records] == list(range(1, 7))
    assert len(records[-1]["eval"]) == 4
