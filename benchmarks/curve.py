"""What CURVE encryption costs per message: a Train message (our codec) sent to a forked echo
peer and back over loopback TCP, plaintext against CURVE, interleaved in the same run.

``python -m benchmarks.curve`` prints the median round trip of each and their ratio for
θ of 10², 10⁴ and 10⁶ float32 parameters. The handshake and the ZAP allow-list check happen
once per connection, so they are left out: this is the cost every round pays.
"""

from __future__ import annotations

import multiprocessing
import statistics
import time

import numpy as np
import zmq

from benchmarks import results_file
from fedhpg.common.wire.codec import decode, encode
from fedhpg.common.wire.protocol import Train

SIZES = (100, 10_000, 1_000_000)


def _echo(endpoint: str, server_public: bytes | None) -> None:
    context = zmq.Context()
    socket = context.socket(zmq.DEALER)
    socket.setsockopt(zmq.LINGER, 0)
    if server_public is not None:
        public, secret = zmq.curve_keypair()
        socket.curve_publickey, socket.curve_secretkey = public, secret
        socket.curve_serverkey = server_public
    socket.connect(endpoint)
    socket.send(b"ready")
    while True:
        frames = socket.recv_multipart(copy=False)
        if len(frames) == 1:
            break
        socket.send_multipart(frames, copy=False)
    socket.close()
    context.term()


def _round_trips(curve: bool, num_params: int, repeats: int) -> list[float]:
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    server_public = None
    if curve:
        server_public, secret = zmq.curve_keypair()
        router.curve_server = True
        router.curve_secretkey = secret
    port = router.bind_to_random_port("tcp://127.0.0.1")
    peer = multiprocessing.get_context("fork").Process(
        target=_echo, args=(f"tcp://127.0.0.1:{port}", server_public)
    )
    peer.start()
    identity = router.recv_multipart()[0]
    message = Train(round=1, theta=np.ones(num_params, dtype=np.float32), agents=[0])
    timings = []
    try:
        for _ in range(repeats + 2):
            started = time.perf_counter()
            router.send_multipart([identity, *encode(message)], copy=False)
            decode(router.recv_multipart(copy=False)[1:])
            timings.append(time.perf_counter() - started)
    finally:
        router.send_multipart([identity, b"stop"])
        peer.join(5)
        if peer.is_alive():
            peer.kill()
        router.close()
        context.term()
    return timings[2:]  # the first two warm up the connection


def measure(num_params: int, slices: int = 5) -> tuple[float, float]:
    """Median round trip (ms) without and with CURVE, from interleaved slices."""
    repeats = 200 if num_params <= 10_000 else 20
    plain: list[float] = []
    curve: list[float] = []
    for _ in range(slices):
        plain += _round_trips(False, num_params, repeats)
        curve += _round_trips(True, num_params, repeats)
    return 1000 * statistics.median(plain), 1000 * statistics.median(curve)


def table(rows: list[tuple[int, float, float]]) -> str:
    """The markdown table of (parameters, plaintext ms, CURVE ms) rows."""
    lines = [
        "| parameters | plaintext round trip (ms) | CURVE round trip (ms) | CURVE − plain (ms) "
        "| ratio |",
        "|---|---|---|---|---|",
    ]
    for size, plain, curve in rows:
        lines.append(
            f"| {size:,} | {plain:.3f} | {curve:.3f} | {curve - plain:+.3f} | {curve / plain:.2f} |"
        )
    return "\n".join(lines)


def summary(rows: list[tuple[int, float, float]]) -> str:
    extra = {size: curve - plain for size, plain, curve in rows}
    return (
        f"CURVE adds hundredths of a millisecond to small messages ({extra[100]:+.2f} ms at "
        f"100 parameters, {extra[10_000]:+.2f} ms at 10⁴) and ~{extra[1_000_000]:.0f} ms to a "
        "million parameters."
    )


def main() -> None:
    rows = [(size, *measure(size)) for size in SIZES]
    print(table(rows))
    results_file.write(
        "curve",
        title="CURVE encryption per message",
        order=210,
        command="python -m benchmarks.curve",
        measures=["common/wire"],
        setup=(
            "A Train message to a forked echo peer and back over loopback TCP, plaintext and "
            "with CURVE, interleaved in 5 slices, medians; the handshake is once per "
            "connection and not in these figures."
        ),
        tables=[results_file.table_from_markdown(table(rows), summary(rows))],
        keep_summaries=False,
    )


if __name__ == "__main__":
    main()
