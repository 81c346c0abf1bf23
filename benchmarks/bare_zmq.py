"""The floor for coordination cost: a bare pyzmq + msgpack broadcast-gather-average.

K forked peer processes each hold a DEALER; the ROUTER sends every peer a msgpack header and
the raw float32 vector, each peer sends the vector back, and the router averages the K replies.
No fedhpg code is involved; the figure is what any framework on ZeroMQ must at least pay.
"""

from __future__ import annotations

import multiprocessing
import statistics
import time

import msgpack
import numpy as np
import zmq


def _peer(endpoint: str, index: int) -> None:
    context = zmq.Context()
    socket = context.socket(zmq.DEALER)
    socket.setsockopt(zmq.IDENTITY, f"peer-{index}".encode())
    socket.setsockopt(zmq.LINGER, 0)
    socket.connect(endpoint)
    socket.send_multipart([b"ready"])
    while True:
        header, payload = socket.recv_multipart(copy=False)
        meta = msgpack.unpackb(header.bytes)
        if meta["stop"]:
            break
        theta = np.frombuffer(payload.buffer, dtype=np.float32)
        socket.send_multipart([msgpack.packb({"n": int(theta.size)}), theta], copy=False)
    socket.close()
    context.term()


def broadcast_gather_ms(num_peers: int, num_params: int, repeats: int = 20) -> float:
    """Median milliseconds of one broadcast + gather + average round."""
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    endpoint = f"tcp://127.0.0.1:{port}"
    fork = multiprocessing.get_context("fork")
    peers = [fork.Process(target=_peer, args=(endpoint, k)) for k in range(num_peers)]
    for peer in peers:
        peer.start()
    identities = [router.recv_multipart()[0] for _ in range(num_peers)]
    theta = np.random.default_rng(0).standard_normal(num_params).astype(np.float32)
    timings = []
    try:
        for _ in range(repeats + 2):
            started = time.perf_counter()
            header = msgpack.packb({"stop": False, "n": num_params})
            for identity in identities:
                router.send_multipart([identity, header, theta], copy=False)
            replies = []
            for _ in identities:
                _, _, payload = router.recv_multipart(copy=False)
                replies.append(np.frombuffer(payload.buffer, dtype=np.float32))
            np.stack(replies).mean(axis=0)
            timings.append(time.perf_counter() - started)
    finally:
        for identity in identities:
            router.send_multipart([identity, msgpack.packb({"stop": True}), b""])
        for peer in peers:
            peer.join(5)
            if peer.is_alive():
                peer.kill()
        router.close()
        context.term()
    return 1000 * statistics.median(timings[2:])
