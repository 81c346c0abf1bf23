"""Several hosts on one machine: the server and each agent in their own Linux network
namespace, joined by veth pairs. A federation completes across them. When one agent's link is
cut mid-run the server behaves as docs/deploy.md says: it presumes the silent
agent dead after the heartbeat liveness window, waits ``server.rejoin_timeout_s`` for it, and
then fails, naming the agent it lost; when the link comes back in time, the agent notices the
silence, reconnects by itself, rejoins at the current round and the run finishes.

Needs root and iproute2 (``ip netns``); skipped with the reason otherwise. The namespaces are
private to this test (addresses 10.77.k.0/30 exist only inside them) and always deleted.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from procs import BIN, QUIET, processes, wait_until

NUM_AGENTS = 2
HEARTBEAT_S = 0.5
LIVENESS = 4
REJOIN_S = 8.0


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


def _namespaces_available() -> str | None:
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    probe = f"fedhpg-probe-{os.getpid()}"
    try:
        _ip("netns", "add", probe)
    except (subprocess.CalledProcessError, OSError) as error:
        return f"cannot create network namespaces here: {error}"
    _ip("netns", "del", probe)
    return None


@pytest.fixture
def hosts() -> Iterator[dict[str, str]]:
    """Namespaces 'server' and 'agent-k', agent k linked to the server by veth s{k} ↔ a{k}."""
    reason = _namespaces_available()
    if reason:
        pytest.skip(reason)
    tag = f"{os.getpid() % 100000}"
    names = {"server": f"fh{tag}-srv", **{f"agent-{k}": f"fh{tag}-a{k}" for k in range(NUM_AGENTS)}}
    created: list[str] = []
    try:
        for namespace in names.values():
            _ip("netns", "add", namespace)
            created.append(namespace)
            _ip("-n", namespace, "link", "set", "lo", "up")
        for k in range(NUM_AGENTS):
            server_end, agent_end = f"s{tag}k{k}", f"a{tag}k{k}"
            _ip("link", "add", server_end, "type", "veth", "peer", "name", agent_end)
            _ip("link", "set", server_end, "netns", names["server"])
            _ip("link", "set", agent_end, "netns", names[f"agent-{k}"])
            _ip("-n", names["server"], "addr", "add", f"10.77.{k}.1/30", "dev", server_end)
            _ip("-n", names[f"agent-{k}"], "addr", "add", f"10.77.{k}.2/30", "dev", agent_end)
            _ip("-n", names["server"], "link", "set", server_end, "up")
            _ip("-n", names[f"agent-{k}"], "link", "set", agent_end, "up")
            names[f"link-{k}"] = server_end
        yield names
    finally:
        for namespace in created:
            subprocess.run(["ip", "netns", "del", namespace], capture_output=True, timeout=10)


def _start(
    started: list, namespace: str, script: str, args: list[str], cwd: Path
) -> subprocess.Popen:
    process = subprocess.Popen(
        ["ip", "netns", "exec", namespace, str(BIN / script), *args],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, **QUIET},
    )  # fmt: skip
    started.append(process)
    return process


def _common(out_dir: Path, rounds: int) -> list[str]:
    return [
        f"rounds={rounds}", f"agents.num_agents={NUM_AGENTS}", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0.002]",
        "server.port=5555", f"server.out_dir={out_dir}", "eval.every=5", "eval.episodes=5",
        f"server.heartbeat_interval_s={HEARTBEAT_S}", f"server.heartbeat_liveness={LIVENESS}",
        f"server.rejoin_timeout_s={REJOIN_S}",
    ]  # fmt: skip


def _federation(hosts: dict[str, str], tmp_path: Path, rounds: int, started: list) -> tuple:
    out_dir = tmp_path / "run"
    common = _common(out_dir, rounds)
    # bind_all inside the server's namespace: reachable only over this test's veth links.
    server = _start(
        started, hosts["server"], "fedhpg-server", [*common, "server.bind_all=true"], tmp_path
    )
    agents = [
        _start(started, hosts[f"agent-{k}"], "fedhpg-agent",
               [*common, f"agent.index={k}", f"server.host=10.77.{k}.1"], tmp_path)
        for k in range(NUM_AGENTS)
    ]  # fmt: skip
    return server, agents, out_dir / "metrics.jsonl"


def test_federation_across_namespaces(hosts: dict[str, str], tmp_path: Path) -> None:
    with processes() as started:
        server, agents, metrics = _federation(hosts, tmp_path, 5, started)
        _, stderr = server.communicate(timeout=120)
        for agent in agents:
            agent.wait(timeout=30)
    assert server.returncode == 0, stderr[-2000:]
    assert [a.returncode for a in agents] == [0] * NUM_AGENTS
    assert len(metrics.read_text().splitlines()) == 5


def _rounds(metrics: Path) -> list[int]:
    return [json.loads(line)["round"] for line in metrics.read_text().splitlines()]


@pytest.mark.slow
@pytest.mark.solo  # gives up within liveness + rejoin timeout + 10 s of the cut
def test_cut_link_fails_the_run_naming_the_agent(hosts: dict[str, str], tmp_path: Path) -> None:
    with processes() as started:
        server, _, metrics = _federation(hosts, tmp_path, 1000, started)
        assert wait_until(lambda: metrics.exists() and len(_rounds(metrics)) >= 2, 60)
        _ip("-n", hosts["server"], "link", "set", hosts["link-1"], "down")
        cut_at = time.monotonic()
        _, stderr = server.communicate(timeout=60)
        waited = time.monotonic() - cut_at
    assert server.returncode == 1
    assert "agent-1 presumed dead: silent for" in stderr
    assert "agent-1 died and did not rejoin within" in stderr
    liveness_s = HEARTBEAT_S * LIVENESS
    assert waited < liveness_s + REJOIN_S + 10, "it gives up after liveness + rejoin timeout"
    rounds = _rounds(metrics)
    assert rounds == list(range(1, len(rounds) + 1)), "every completed round was recorded"


@pytest.mark.slow
@pytest.mark.solo  # a link down for 2 s of heartbeats + 1.5 s, short of rejoin_timeout_s
def test_healed_link_rejoins_and_the_run_finishes(hosts: dict[str, str], tmp_path: Path) -> None:
    rounds = 40
    with processes() as started:
        server, agents, metrics = _federation(hosts, tmp_path, rounds, started)
        assert wait_until(lambda: metrics.exists() and len(_rounds(metrics)) >= 2, 60)
        _ip("-n", hosts["server"], "link", "set", hosts["link-1"], "down")
        # Down long enough for both sides to give up on each other, short of rejoin_timeout_s.
        time.sleep(HEARTBEAT_S * LIVENESS + 1.5)
        _ip("-n", hosts["server"], "link", "set", hosts["link-1"], "up")
        _, stderr = server.communicate(timeout=120)
        for agent in agents:
            agent.wait(timeout=30)
        agent_errors = agents[1].stderr.read() if agents[1].stderr else ""
    assert server.returncode == 0, stderr[-2000:]
    assert [a.returncode for a in agents] == [0] * NUM_AGENTS
    assert "agent-1 presumed dead" in stderr and "agent-1 rejoined after" in stderr
    assert "no word from the server" in agent_errors, "the agent noticed the silence itself"
    assert _rounds(metrics) == list(range(1, rounds + 1))
