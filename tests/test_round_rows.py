"""A round's θ_k gathered into one [K, d] matrix as they arrive (server/round_rows.py).

Rows land at their agent's place whatever order a batch lists them in, and the accepted ones
are handed on as that matrix (or a compact copy); over real sockets a host's batch with bad
rows rejects those agents only, the others' θ_k arriving bit for bit, their statistics
gathered from the batches' columns.
"""

from __future__ import annotations

import numpy as np
import torch
import zmq

from fedhpg.common.configuration.settings.server import ServerConfig
from fedhpg.common.heterogeneity.variants import range_digest
from fedhpg.common.records.types import UpdateColumns, UpdateStats
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import Error, Hello, Train, Update, Welcome
from fedhpg.server.pools.zmq_pool import ZmqAgentPool
from fedhpg.server.round_rows import ALIGNMENT, RoundRows
from fedhpg.server.validation import NON_FINITE, Reject, UpdateCheck

STATS = UpdateStats(trajectories=4, env_steps=80, compute_s=0.1, train_return=20.0)


def _thetas(rows: int, d: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((rows, d)).astype(np.float32)


def test_rows_land_at_their_agents_place_in_any_order() -> None:
    thetas = _thetas(6, 1500)
    rows = RoundRows([10, 11, 12, 13, 20, 21], 1500)
    assert rows.matrix.ctypes.data % ALIGNMENT == 0
    # a batch listing its agents out of order, with a row left out (a rejected agent)
    rows.put([21, 10, 11, 13], thetas, [5, 0, 1, 3])
    rows.put([12, 20], thetas[[2, 4]], [0, 1])
    assert rows.block([10, 11, 12, 13, 20, 21]) is rows.matrix
    assert np.array_equal(rows.matrix, thetas)
    compact = rows.block([10, 13, 21])
    assert compact.ctypes.data % ALIGNMENT == 0
    assert np.array_equal(compact, thetas[[0, 3, 5]])


def test_bad_rows_of_a_batch_reject_their_agents_only() -> None:
    d, count = 3000, 5
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.ROUTER_MANDATORY, 1)
    host = context.socket(zmq.DEALER)
    try:
        port = router.bind_to_random_port("tcp://127.0.0.1")
        digests = [f"digest-{k}" for k in range(count)]
        pool = ZmqAgentPool(
            socket=router,
            num_agents=count,
            check=UpdateCheck(num_params=d),
            env_signature={"spaces": "x"},
            variant_digests=digests,
            run_settings={},
            run_id="test",
            max_bytes=1 << 26,
            settings=ServerConfig(),
        )
        host.setsockopt(zmq.LINGER, 0)
        host.setsockopt(zmq.IDENTITY, b"host-0-5#0")
        host.connect(f"tcp://127.0.0.1:{port}")
        hello = Hello(
            id="host-0-5",
            first=0,
            count=count,
            env_signature={"spaces": "x"},
            variant_digest=range_digest(digests),
        )
        host.send_multipart(encode(hello))
        pool.wait_for_agents(10)
        assert host.poll(5000) and isinstance(decode(host.recv_multipart()), Welcome)
        thetas = _thetas(count, d, seed=1)
        thetas[1, 7] = np.nan
        thetas[4, -1] = -np.inf
        thetas[3] = np.float32(3e38)  # finite: its row sum overflows, the row is still fine
        # two batches, agents listed out of order: queued before the round collects them
        host.send_multipart(
            encode(
                Update(
                    round=1,
                    agents=[4, 0, 3],
                    thetas=thetas[[4, 0, 3]],
                    stats=UpdateColumns.of([STATS] * 3),
                )
            )
        )
        host.send_multipart(
            encode(
                Update(
                    round=1,
                    agents=[2, 1],
                    thetas=thetas[[2, 1]],
                    stats=UpdateColumns.of([STATS] * 2),
                )
            )
        )
        answers = pool.train(1, torch.zeros(d), range(count))
        replies = []
        while host.poll(200):
            replies.append(decode(host.recv_multipart()))
    finally:
        host.close(linger=0)
        router.close(linger=0)
        context.term()
    result = answers.result
    assert result.agents == [0, 2, 3]
    assert np.array_equal(result.thetas, thetas[[0, 2, 3]])
    assert list(result.stats) == [STATS] * 3
    failures = {k: (r.code, r.reason) for k, r in answers.failures.items()}
    assert failures == {k: (Reject.NON_FINITE, NON_FINITE) for k in ("agent-1", "agent-4")}
    assert any(isinstance(reply, Train) for reply in replies)
    refusals = [(r.code, r.reason) for r in replies if isinstance(r, Error)]
    assert refusals == [
        ("bad_update", f"agent-4: {NON_FINITE}"),
        ("bad_update", f"agent-1: {NON_FINITE}"),
    ]
    assert result.thetas.ctypes.data % ALIGNMENT == 0  # a compact copy of the accepted rows
