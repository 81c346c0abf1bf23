"""Agent hosts: one process serving many logical agents over one connection.

Placement never changes θ̃: one process per agent, hosts of 3 (3 + 3 + 1) and of 7, and the
in-process runner end bit for bit alike. A killed host's agents die together and rejoin
together when ``fedhpg-run`` restarts it, and the run ends as if nothing happened. A host
that answers for agents outside its range, or sends an oversized batch, is refused message
by message while its honest answers still count. Real processes, loopback TCP.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import zmq
from peers import raw_frames
from procs import child_named, child_pids, free_port, processes, start, wait_until

from fedhpg.common.heterogeneity.variants import (
    range_digest,
    run_variants,
    variant_digest,
    variant_of,
)
from fedhpg.common.learning.group import make_agent_group
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.records.types import UpdateColumns
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import (
    MAX_BATCH_ANSWERS,
    Error,
    Evaluate,
    Evaluation,
    Heartbeat,
    Hello,
    Shutdown,
    Train,
    Update,
    Welcome,
)
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

TIMEOUT_S = 120
RUN = [
    "rounds=3", "seed=5", "agents.num_agents=7", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[2]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "agents.virtual_clock=true", "eval.every=3", "eval.episodes=2",
]  # fmt: skip


def _fedhpg_run(tmp_path: Path, keys: list[str], name: str) -> tuple[torch.Tensor, dict]:
    out_dir = tmp_path / name
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*keys, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra' / name}"],
            cwd=tmp_path,
        )
        stdout, stderr = launcher.communicate(timeout=TIMEOUT_S)
    assert launcher.returncode == 0, (stdout + stderr)[-3000:]
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    rounds = int(next(k for k in keys if k.startswith("rounds=")).split("=")[1])
    assert checkpoint is not None and checkpoint.round == rounds
    return checkpoint.theta, json.loads((out_dir / "summary.json").read_text())


# CartPole variants, B_k and τ_k from the population: the compiled backend samples and
# differentiates for every agent of every algorithm (rows of 1, 3 or 7 agents; a lone agent is
# a group of one); agent 2 flips its update's sign after its local update.
ENGINE_RUN = [
    "env=cartpole", "agents=population", "rounds=3", "seed=5", "agents.num_agents=7",
    "agents.clock=counted", "eval.every=3", "eval.episodes=2", "attack.kind=sign_flip",
    "attack.agents=[2]", "agents.latencies_s=[0.002]",
    "agents.bandwidths_mbps=[0,25,0,40,10,0,25]",
]  # fmt: skip


ALGORITHM_RUNS = {
    "fedhpg": ENGINE_RUN,
    "fedhpgvr": [*ENGINE_RUN, "algo=fedhpgvr"],
    "fedpgbr": [*ENGINE_RUN, "algo=fedpgbr", "strategy=fedpgbr"],
}


@pytest.mark.parametrize(
    "algorithm",
    [
        "fedhpg",
        # ~16 s: make test-long. fast cover: tests/test_hosts.py::
        # test_theta_does_not_depend_on_the_placement_of_the_agents[fedhpg] (placement) and
        # tests/test_hosts.py::test_fedhpgvr_on_hosts_mixed_with_a_lone_agent_is_the_in_process_run
        pytest.param("fedhpgvr", marks=pytest.mark.slow),
        pytest.param("fedpgbr", marks=pytest.mark.slow),  # the longest (~14 s): make test-long
    ],
)
def test_theta_does_not_depend_on_the_placement_of_the_agents(
    tmp_path: Path, algorithm: str
) -> None:
    """Nor does any agent's emulated time on the counted clock: a host emulates its agents'
    devices column-wise (common/heterogeneity/device.py's DeviceColumns), a lone agent and the
    in-process pool one DeviceModel at a time."""
    keys_of_run = ALGORITHM_RUNS[algorithm]
    run = compose(keys_of_run)
    records: list = []
    expected = run_in_process(run, on_round=[lambda record, _: records.append(record)])
    assert not torch.equal(expected, initial_theta(variant_of(run, 0), run))
    emulated = [dict(zip(r.result.agents, r.result.stats.emulated_s, strict=True)) for r in records]
    speeds = [dict(zip(r.result.agents, r.result.stats.speed, strict=True)) for r in records]
    assert len({e for r in emulated for e in r.values()}) > 7, "the agents' times differ"
    for per_host in (1, 3, 7):  # 7 processes; hosts of 3 + 3 + 1; one host of 7
        keys = [*keys_of_run, f"agents.per_host={per_host}"]
        theta, summary = _fedhpg_run(tmp_path, keys, str(per_host))
        assert torch.equal(theta, expected), per_host
        lines = (tmp_path / str(per_host) / "metrics.jsonl").read_text().splitlines()
        rounds = [json.loads(line)["agents"] for line in lines]
        assert [{a["index"]: a["emulated_s"] for a in r} for r in rounds] == (emulated), per_host
        assert [{a["index"]: a["speed"] for a in r} for r in rounds] == (speeds), per_host
        assert summary["agent_deaths"] == 0 and summary["rejected_messages"] == 0
        assert sorted(summary["eval"]) == sorted(f"agent-{k}" for k in range(7))


def test_a_killed_host_is_restarted_and_its_agents_rejoin(tmp_path: Path) -> None:
    keys = [
        "rounds=30", "seed=2", "agents.num_agents=6", "agents.per_host=3",
        "agents.budget.batch_size=[16]", "agents.budget.local_iters=[1]", "agents.speeds=[1]",
        "agents.step_delays_s=[0]", "eval.every=30", "eval.episodes=2",
        "server.heartbeat_interval_s=0.25", "server.heartbeat_liveness=4",
    ]  # fmt: skip
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*keys, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        metrics = out_dir / "metrics.jsonl"
        assert wait_until(lambda: metrics.exists() and len(metrics.read_text().split()) >= 2, 60)
        children = child_pids(launcher.pid)
        assert len(children) == 3, children  # the server and two hosts
        os.kill(child_named(launcher.pid, "host-3-5"), signal.SIGKILL)
        stdout, stderr = launcher.communicate(timeout=TIMEOUT_S)
    logs = stdout + stderr
    assert launcher.returncode == 0, logs[-3000:]
    assert "host-3-5 exited with status -9; restarting it" in logs
    assert "host host-3-5 (agents 3..5) presumed dead" in logs
    assert "host host-3-5 (agents 3..5) rejoined (3 agents back" in logs
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["agent_deaths"] == 3 and summary["agent_rejoins"] == 3
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 30
    assert torch.equal(checkpoint.theta, run_in_process(compose(keys)))  # lost work redone


VR = ["algo=fedhpgvr", "agents.budget={batch_size:[4],inner_steps:[2],mini_batch_size:[2]}"]


def test_fedhpgvr_on_hosts_mixed_with_a_lone_agent_is_the_in_process_run(tmp_path: Path) -> None:
    """By hand: ``fedhpg-agent agent.first=0 agent.count=3`` and ``agent.first=3`` serve
    agents 0..5, a plain ``fedhpg-agent agent.index=6`` the last one (a mixed federation)."""
    keys = [*RUN, *VR]
    out_dir = tmp_path / "run"
    wire = [f"server.port={free_port()}", f"server.out_dir={out_dir}"]
    with processes() as started:
        server = start(started, "fedhpg-server", [*keys, *wire], cwd=tmp_path)
        agents = [
            start(started, "fedhpg-agent", [*keys, *wire, *placement], cwd=tmp_path)
            for placement in (
                ["agent.first=0", "agent.count=3"],
                ["agent.first=3", "agent.count=3"],
                ["agent.index=6"],
            )
        ]
        _, stderr = server.communicate(timeout=TIMEOUT_S)
        for agent in agents:
            agent.wait(timeout=30)
    assert server.returncode == 0, stderr[-3000:]
    assert [agent.returncode for agent in agents] == [0, 0, 0]
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 3
    assert torch.equal(checkpoint.theta, run_in_process(compose(keys)))
    summary = json.loads((out_dir / "summary.json").read_text())
    assert sorted(summary["eval"]) == sorted(f"agent-{k}" for k in range(7))


HOSTILE_RUN = [
    "rounds=2", "seed=1", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "eval.every=2", "eval.episodes=2", "server.heartbeat_interval_s=0.25",
]  # fmt: skip


def _dealer(context: zmq.Context, port: int, identity: bytes) -> zmq.Socket:
    socket = context.socket(zmq.DEALER)
    socket.setsockopt(zmq.IDENTITY, identity)
    socket.setsockopt(zmq.LINGER, 0)
    socket.connect(f"tcp://127.0.0.1:{port}")
    return socket


def _reply(socket: zmq.Socket, timeout_s: float = 10.0) -> object:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if socket.poll(100):
            message = decode(socket.recv_multipart())
            if not isinstance(message, Heartbeat):
                return message
    raise AssertionError("no reply from the server")


def test_a_host_claiming_foreign_agents_or_a_huge_batch_is_refused_and_the_run_goes_on(
    tmp_path: Path,
) -> None:
    """A scripted host serves agents 0..1 honestly (with the real agent group), but first
    sends, each round: answers for agent 5 (outside its range), a batch of 300 rows (over the
    bound), rows that do not match their stats. A second host claiming agent 1 is refused as
    a duplicate. The server refuses each of those and ends with the in-process θ̃."""
    run = compose(HOSTILE_RUN)
    variants = run_variants(run)
    group = make_agent_group(run, [0, 1])
    port = free_port()
    out_dir = tmp_path / "run"
    context = zmq.Context()
    host = _dealer(context, port, b"host-0-1#1")
    refusals: list[str] = []
    with processes() as started:
        server = start(
            started,
            "fedhpg-server",
            [*HOSTILE_RUN, f"server.port={port}", f"server.out_dir={out_dir}"],
            cwd=tmp_path,
        )
        host.send_multipart(
            encode(
                Hello(
                    id="host-0-1",
                    first=0,
                    count=2,
                    env_signature=variants[0].signature(),
                    variant_digest=range_digest([variant_digest(run, v) for v in variants]),
                )
            )
        )
        assert isinstance(_reply(host, 30), Welcome)
        rival = _dealer(context, port, b"host-1-1#2")
        rival.send_multipart(
            encode(
                Hello(
                    id="host-1-1",
                    first=1,
                    count=1,
                    env_signature=variants[1].signature(),
                    variant_digest=range_digest([variant_digest(run, variants[1])]),
                )
            )
        )
        refused = _reply(rival)
        assert isinstance(refused, Error) and refused.code == "duplicate_agent", refused
        rival.close()
        deadline = time.monotonic() + TIMEOUT_S
        last_beat = 0.0
        while time.monotonic() < deadline:
            if time.monotonic() - last_beat > 0.2:
                host.send_multipart(encode(Heartbeat()))
                last_beat = time.monotonic()
            if not host.poll(50):
                continue
            message = decode(host.recv_multipart())
            if isinstance(message, Shutdown):
                assert message.complete, message.reason
                break
            if isinstance(message, Error):
                refusals.append(message.code)
            elif isinstance(message, Train):
                theta = torch.from_numpy(np.array(message.theta))
                results = group.train(message.round, theta, message.agents).result
                stats = results.stats_of(0)
                row = results.theta_of(0)[None]
                foreign = Update(
                    round=message.round, agents=[5], thetas=row, stats=UpdateColumns.of([stats])
                )
                rows = MAX_BATCH_ANSWERS + 44
                huge = raw_frames(
                    Update(
                        round=message.round,
                        agents=[0] * rows,
                        thetas=np.repeat(row, rows, axis=0),
                        stats=UpdateColumns.of([stats] * rows),
                    )
                )
                mismatch = Update(
                    round=message.round,
                    agents=[0, 1],
                    thetas=row,
                    stats=UpdateColumns.of([stats, stats]),
                )
                for frames in (encode(foreign), huge, raw_frames(mismatch)):
                    host.send_multipart(frames)
                host.send_multipart(encode(results))
            elif isinstance(message, Evaluate):
                theta = torch.from_numpy(np.array(message.theta))
                evaluations = group.evaluate(message.round, theta, message.episodes, message.agents)
                host.send_multipart(
                    encode(
                        Evaluation(
                            round=message.round,
                            agents=list(message.agents),
                            stats=[evaluations[k] for k in message.agents],
                        )
                    )
                )
        _, stderr = server.communicate(timeout=TIMEOUT_S)
    host.close()
    context.term()
    group.close()
    assert server.returncode == 0, stderr[-3000:]
    assert "Traceback" not in stderr
    assert refusals.count("bad_index") == 2 and refusals.count("bad_fields") == 2, refusals
    assert refusals.count("bad_update") == 2, refusals
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["rejected_messages"] >= 7  # 3 per round and the rival's hello
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 2
    assert torch.equal(checkpoint.theta, run_in_process(compose(HOSTILE_RUN)))


def test_placement_is_neither_fixed_on_resume_nor_an_experiment_difference() -> None:
    from fedhpg.common.configuration.config import to_dict
    from fedhpg.common.configuration.run_keys import fixed_difference
    from fedhpg.server.commands.plot import _compared

    run = to_dict(compose(["agents.per_host=1"]))
    assert fixed_difference(run, to_dict(compose(["agents.per_host=500"]))) is None
    assert fixed_difference(run, to_dict(compose(["agents.speeds=[2]"]))) is not None
    assert not _compared("agents.per_host") and _compared("agents.num_agents")
