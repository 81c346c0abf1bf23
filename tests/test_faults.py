"""Bad input against a running server: every kind is rejected with a reason, and the
federation still finishes with exactly the right θ. Real processes, loopback TCP."""

from __future__ import annotations

import subprocess
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
import zmq
from procs import BIN, free_port, processes, start, wait_until

from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.records.types import UpdateColumns, UpdateStats
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import PROTOCOL_VERSION, Error, Hello, Update
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

TIMEOUT_S = 120


def _overrides(port: int, out_dir: Path) -> list[str]:
    return [
        "rounds=10",
        "seed=3",
        "agents.num_agents=3",
        "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[2]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0.003]",
        "eval.every=3",
        "eval.episodes=5",
        f"server.port={port}",
        f"server.out_dir={out_dir}",
    ]


class Rogue:
    """A peer that is not a well-behaved agent."""

    def __init__(self, context: zmq.Context, port: int, identity: bytes) -> None:
        self.socket = context.socket(zmq.DEALER)
        self.socket.setsockopt(zmq.IDENTITY, identity)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.socket.connect(f"tcp://127.0.0.1:{port}")

    def ask(self, frames: list, timeout_s: float = 20.0) -> Error | None:
        self.socket.send_multipart(frames)
        if not self.socket.poll(int(timeout_s * 1000)):
            return None
        reply = decode(self.socket.recv_multipart())
        assert isinstance(reply, Error), reply
        return reply

    def close(self) -> None:
        self.socket.close()


def _header(**overrides: object) -> bytes:
    header = {"v": PROTOCOL_VERSION, "type": "heartbeat", "fields": {}, "arrays": []}
    header.update(overrides)
    return msgpack.packb(header)


def _update(theta: np.ndarray) -> list:
    stats = UpdateStats(trajectories=1, env_steps=1, compute_s=0.0, train_return=0.0)
    return encode(Update(round=1, agents=[0], thetas=theta[None], stats=UpdateColumns.of([stats])))


@pytest.mark.slow
def test_server_survives_bad_input_and_finishes_right(tmp_path: Path) -> None:
    port = free_port()
    out_dir = tmp_path / "run"
    overrides = _overrides(port, out_dir)
    num_params = 25 * 4
    context = zmq.Context()
    try:
        with processes() as started:
            server = start(started, "fedhpg-server", overrides, cwd=tmp_path)
            rogue = Rogue(context, port, b"rogue#1")
            cases = {
                "malformed": [b"\x00garbage\xff"],
                "version": [_header(v=99)],
                "unknown_type": [_header(type="steal_weights")],
                "bad_fields": [_header(type="evaluation", fields={"round": "one", "stats": {}})],
            }
            for code, frames in cases.items():
                reply = rogue.ask(frames)
                assert reply is not None and reply.code == code, (code, reply)
            for theta, reason in [
                (np.zeros(7, dtype=np.float32), "shape"),
                (np.zeros(num_params, dtype=np.float64), "float32"),
                (np.full(num_params, np.nan, dtype=np.float32), "NaN"),
            ]:
                reply = rogue.ask(_update(theta))
                assert reply is not None and reply.code == "bad_update" and reason in reply.reason
            reply = rogue.ask(_update(np.zeros(num_params, dtype=np.float32)))
            assert reply is not None and reply.code == "not_registered"
            bad_signature = Hello(
                id="mallory",
                first=0,
                count=1,
                names_agent=True,
                env_signature={"observation": "Box(4)", "action": "Discrete(2)"},
                variant_digest="",
            )
            reply = rogue.ask(encode(bad_signature))
            assert reply is not None and reply.code == "env_signature"
            signature = run_variants(
                compose([o for o in overrides if not o.startswith("server.")])
            )[0].signature()
            reply = rogue.ask(
                encode(Hello(id="mallory", first=0, count=1, names_agent=True,
                             env_signature=signature, variant_digest="not-the-run's"))
            )  # fmt: skip
            assert reply is not None and reply.code == "variant_mismatch"
            for first, count in ((9, 1), (1, 3)):  # beyond the run's three agents
                reply = rogue.ask(
                    encode(Hello(id="mallory", first=first, count=count, env_signature={},
                                 variant_digest=""))
                )  # fmt: skip
                assert reply is not None and reply.code == "bad_index"
            # Over the run's cap (a 1 MiB header and θ): libzmq drops the connection, no reply.
            oversized = Rogue(context, port, b"rogue#2")
            assert oversized.ask([_header(), b"\x00" * (2 << 20)], timeout_s=1.0) is None
            oversized.close()

            for index in range(3):
                start(started, "fedhpg-agent", [*overrides, f"agent.index={index}"], cwd=tmp_path)
            metrics = out_dir / "metrics.jsonl"
            assert wait_until(lambda: metrics.exists() and metrics.read_text().strip(), TIMEOUT_S)
            duplicate = start(
                started,
                "fedhpg-agent",
                [*overrides, "agent.index=0", "agent.connect_timeout_s=20"],
                cwd=tmp_path,
            )
            # Mid-run garbage and a wrong-shape update from the rogue.
            assert rogue.ask([b"\x91\xc1"]).code == "malformed"  # type: ignore[union-attr]
            assert rogue.ask(_update(np.zeros(3, dtype=np.float32))).code == "bad_update"  # type: ignore[union-attr]
            rogue.close()

            _, duplicate_err = duplicate.communicate(timeout=TIMEOUT_S)
            assert duplicate.returncode == 1
            assert "duplicate_agent" in duplicate_err
            _, server_err = server.communicate(timeout=TIMEOUT_S)
            assert server.returncode == 0, server_err[-3000:]
            for process in started[1:]:
                process.wait(timeout=30)
            assert all(p.returncode == 0 for p in started[1:4]), [p.returncode for p in started]
    finally:
        context.destroy(linger=0)  # also closes the rogues' sockets when an assertion failed
    assert "rejected message from rogue#1" in server_err
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 10
    expected = run_in_process(compose([o for o in overrides if not o.startswith("server.")]))
    assert torch.equal(checkpoint.theta, expected)


def test_missing_agents_are_named_after_the_timeout(tmp_path: Path) -> None:
    port = free_port()
    overrides = [
        "agents.num_agents=3",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        f"server.port={port}",
        "server.register_timeout_s=4",
        f"server.out_dir={tmp_path / 'run'}",
    ]
    with processes() as started:
        server = start(started, "fedhpg-server", overrides, cwd=tmp_path)
        start(started, "fedhpg-agent", [*overrides, "agent.index=1"], cwd=tmp_path)
        _, stderr = server.communicate(timeout=TIMEOUT_S)
    assert server.returncode == 1
    assert "only 1 of 3 agents registered" in stderr
    assert "missing: agents 0, 2 (2 in all)" in stderr


def test_missing_agents_take_one_short_line_at_any_k() -> None:
    from fedhpg.server.pools.zmq_pool import index_ranges

    missing = [*range(832, 1000), 5]
    assert index_ranges(missing) == "agents 5, 832-999 (169 in all)"
    scattered = index_ranges(range(0, 2000, 2))
    assert len(scattered) < 80 and scattered.endswith(", … (1000 in all)")


def test_agent_gives_up_clearly_without_a_server(tmp_path: Path) -> None:
    overrides = [
        "agents.num_agents=1",
        "agents.budget.batch_size=[4]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        f"server.port={free_port()}",
        "agent.connect_timeout_s=2",
    ]
    result = subprocess.run(
        [str(BIN / "fedhpg-agent"), *overrides],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert result.returncode == 1
    assert "no answer from the server" in result.stderr and "Traceback" not in result.stderr
    (last,) = [line for line in result.stderr.splitlines() if "no answer" in line]
    assert last.startswith("error: agent 0: no answer from the server at tcp://"), last
    assert " ERROR " not in result.stderr
