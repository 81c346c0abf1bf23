"""Agent hosts at scale: K logical agents on a few host processes (``agents.per_host``).

:func:`measure`: start-up to the end of round 1, peak PSS of the whole federation, and the
coordination time per round per participating agent (round time − the slowest host's wall
time on the round, over the agents that took part: the wire both ways, the server's checks
and the strategy's aggregation), from a real ``fedhpg-run`` federation on loopback.

:func:`server_side_us`: the server's own time per agent of a round — decoding the hosts'
batches, checking every row, collecting — with a real ROUTER, two DEALER "hosts" of 500
agents each in this process, and the answers already queued (no training, no aggregation).

    python -m benchmarks.hosts --agents 1000 --per-host 500 --rounds 3
    python -m benchmarks.hosts --server-side 10000
    python -m benchmarks.hosts --codec
    python -m benchmarks.hosts --host-round [--agents 10000 --per-host 5000]

:func:`batch_codec_us`: one host's ``Update`` of 256 agents, built and encoded, then
decoded with every agent's stats read back, in this process.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.runtime import _federation


def measure(agents: int, per_host: int, rounds: int, family: str, extra: list[str]) -> dict:
    overrides = [
        f"rounds={rounds}",
        f"env.family={family}",
        f"agents.num_agents={agents}",
        f"agents.per_host={per_host}",
        "agents.budget.batch_size=[2]",
        "agents.budget.local_iters=[1]",
        "agents.speeds=[1]",
        "agents.step_delays_s=[0]",
        "agents.virtual_clock=true",
        f"eval.every={rounds + 1}",
        "eval.episodes=1",
        "server.register_timeout_s=300",
        *extra,
    ]
    with tempfile.TemporaryDirectory() as tmp:
        records, first_round_s, peak = _federation(
            overrides, Path(tmp), sample_memory=True, poll_s=0.05
        )
    overhead = [
        (r["round_time_s"] - max(a["local_wall_s"] for a in r["agents"])) / len(r["agents"])
        for r in records
    ]
    return {
        "agents": agents,
        "per_host": per_host,
        "start_to_round_1_s": first_round_s,
        "peak_pss_mib": peak / 2**20,
        "round_time_s": [r["round_time_s"] for r in records],
        "server_us_per_agent_round": 1e6 * statistics.median(overhead),
    }


def server_side_us(num_params: int, rounds: int = 5) -> list[float]:
    """Microseconds per agent of ``ZmqAgentPool.train`` for 2 hosts × 500 agents whose
    ``Update`` es (256 rows at most each) are queued before the round starts."""
    import numpy as np
    import torch
    import zmq

    from fedhpg.common.configuration.settings.server import ServerConfig
    from fedhpg.common.heterogeneity.variants import range_digest
    from fedhpg.common.records.types import UpdateColumns, UpdateStats
    from fedhpg.common.wire.codec import encode
    from fedhpg.common.wire.protocol import MAX_BATCH_ANSWERS, Hello, Update
    from fedhpg.server.pools.zmq_pool import ZmqAgentPool
    from fedhpg.server.validation import UpdateCheck

    k, per_host = 1000, 500
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.ROUTER_MANDATORY, 1)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    digests = [f"digest-{i}" for i in range(k)]
    pool = ZmqAgentPool(
        socket=router, num_agents=k, check=UpdateCheck(num_params=num_params),
        env_signature={"spaces": "x"}, variant_digests=digests, run_settings={}, run_id="bench",
        max_bytes=1 << 30, settings=ServerConfig(),
    )  # fmt: skip
    hosts = []
    for first in range(0, k, per_host):
        host = context.socket(zmq.DEALER)
        host.setsockopt(zmq.IDENTITY, f"host-{first}#0".encode())
        host.connect(f"tcp://127.0.0.1:{port}")
        host.send_multipart(
            encode(
                Hello(
                    id=f"host-{first}", first=first, count=per_host,
                    env_signature={"spaces": "x"},
                    variant_digest=range_digest(digests[first : first + per_host]),
                )
            )
        )  # fmt: skip
        hosts.append((first, host))
    pool.wait_for_agents(10)
    stats = UpdateStats(
        trajectories=2, env_steps=40, compute_s=0.01, train_return=1.0, local_wall_s=0.5
    )
    rng = np.random.default_rng(0)
    times = []
    for _ in range(rounds):
        for first, host in hosts:
            while host.poll(0):
                host.recv_multipart()
            for start in range(first, first + per_host, MAX_BATCH_ANSWERS):
                agents = list(range(start, min(start + MAX_BATCH_ANSWERS, first + per_host)))
                thetas = (rng.standard_normal((len(agents), num_params)) * 0.01).astype(np.float32)
                host.send_multipart(
                    encode(
                        Update(
                            round=1,
                            agents=agents,
                            thetas=thetas,
                            stats=UpdateColumns.of([stats] * len(agents)),
                        )
                    )
                )
        time.sleep(0.5)  # every batch queued at the server
        started = time.perf_counter()
        answers = pool.train(1, torch.zeros(num_params), range(k))
        times.append(1e6 * (time.perf_counter() - started) / k)
        assert len(answers.result) == k, answers.failures
    for _, host in hosts:
        host.close()
    router.close()
    context.term()
    return times


def batch_codec_us(num_params: int = 386, agents: int = 256, repeats: int = 5) -> dict:
    """Microseconds per agent to build and encode one host's ``Update`` (the host's side)
    and to decode it and read back every agent's ``UpdateStats`` (the server's), median of
    ``repeats`` timings of 40 messages each; and the header's size."""
    import numpy as np

    from fedhpg.common.records.types import UpdateColumns, UpdateStats
    from fedhpg.common.wire.codec import decode, encode
    from fedhpg.common.wire.protocol import Update

    rng = np.random.default_rng(0)
    records = [
        UpdateStats(
            trajectories=int(rng.integers(4, 48)),
            env_steps=int(rng.integers(100, 9000)),
            compute_s=float(rng.random() * 1e-3),
            train_return=float(rng.random() * 30),
            emulated_s=float(rng.random()),
            speed=float(rng.random() + 0.5),
            local_wall_s=0.1,
            algorithm={
                "engine_sample_s": float(rng.random()),
                "engine_gradient_s": float(rng.random()),
            },
        )
        for _ in range(agents)
    ]
    thetas = rng.standard_normal((agents, num_params)).astype(np.float32)

    def build_and_encode() -> list:
        columns = UpdateColumns.of(records)
        batch = Update(round=3, agents=list(range(agents)), thetas=thetas, stats=columns)
        return encode(batch)

    frames = [bytes(f) for f in build_and_encode()]

    def decode_and_read() -> None:
        message = decode(frames)
        assert isinstance(message, Update)
        list(message.stats)

    def per_agent(work: Any) -> float:
        times = []
        for _ in range(repeats):
            started = time.perf_counter()
            for _ in range(40):
                work()
            times.append((time.perf_counter() - started) / 40 / agents * 1e6)
        return statistics.median(times)

    return {
        "encode_us_per_agent": per_agent(build_and_encode),
        "decode_us_per_agent": per_agent(decode_and_read),
        "header_bytes": len(frames[0]),
    }


def host_round_us(agents: int = 1000, per_host: int = 500, rounds: int = 8) -> dict:
    """One agent host's round in this process, no sockets: ``AgentWork.answer`` on a
    ``Train`` of its ``per_host`` CartPole population agents (all of them, or 500
    drawn anew each round where the host holds more), at one fixed θ; the time outside the
    engine's two kernels per agent (budgets, streams, results, device emulation, the
    batches built) and the answers' encoding, medians over the rounds after the first."""
    import threading

    import numpy as np
    import torch

    from fedhpg.agent.work import AgentWork
    from fedhpg.common.learning.batched import kernels
    from fedhpg.common.runtime.cli import compose
    from fedhpg.common.wire.codec import encode
    from fedhpg.common.wire.protocol import Train
    from fedhpg.common.wire.transport import max_message_bytes

    torch.set_num_threads(1)
    run = compose(
        [
            "env=cartpole", "agents=population", f"agents.num_agents={agents}",
            f"agents.per_host={per_host}", "agents.clock=counted", "agent.first=0",
            f"agent.count={per_host}",
        ]
    )  # fmt: skip
    work = AgentWork(run, range(per_host), label="bench")
    started = time.perf_counter()
    group = work.build(run)
    group_s = time.perf_counter() - started
    max_bytes = max_message_bytes(run.server)
    in_kernels = [0.0]
    originals = {name: getattr(kernels, name) for name in ("sample_rows", "row_gradients")}

    def timed(kernel: Any) -> Any:
        def call(*args: Any) -> None:
            begin = time.perf_counter()
            kernel(*args)
            in_kernels[0] += time.perf_counter() - begin

        return call

    rng = np.random.default_rng(0)
    theta = (rng.standard_normal(group.num_params) * 0.1).astype(np.float32)
    outside, encoding = [], []
    try:
        for name, kernel in originals.items():
            setattr(kernels, name, timed(kernel))
        for round_index in range(1, rounds + 1):
            chosen = range(per_host) if per_host <= 500 else rng.choice(per_host, 500, False)
            request = Train(round=round_index, theta=theta, agents=sorted(map(int, chosen)))
            in_kernels[0] = 0.0
            begin = time.perf_counter()
            answers = work.answer(request, threading.Event(), max_bytes)
            wall = time.perf_counter() - begin
            begin = time.perf_counter()
            for answer in answers:
                encode(answer)
            encoding.append(time.perf_counter() - begin)
            outside.append((wall - in_kernels[0]) / len(request.agents))
    finally:
        for name, kernel in originals.items():
            setattr(kernels, name, kernel)
        work.close()
    return {
        "agents_per_round": min(per_host, 500),
        "group_and_prepare_s": group_s,
        "outside_kernels_us_per_agent": 1e6 * statistics.median(outside[1:]),
        "encode_ms_per_round": 1e3 * statistics.median(encoding[1:]),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--per-host", type=int, default=500)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--family", default="gridworld")
    parser.add_argument("--server-side", type=int, metavar="D", help="num_params: pool only")
    parser.add_argument("--codec", action="store_true", help="one host Update's codec only")
    parser.add_argument("--host-round", action="store_true", help="one host's round, no sockets")
    parser.add_argument("extra", nargs="*")
    args = parser.parse_args()
    if args.codec:
        print(batch_codec_us())
    elif args.host_round:
        print(host_round_us(args.agents, args.per_host))
    elif args.server_side:
        times = server_side_us(args.server_side)
        print(f"server µs per agent per round (d={args.server_side}): {times}")
    else:
        print(measure(args.agents, args.per_host, args.rounds, args.family, args.extra))
