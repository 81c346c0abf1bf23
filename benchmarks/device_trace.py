"""Write docs/device-trace.csv, the example population trace (``agents.population.kind=trace``).

The trace is synthetic: no device was measured. Twenty devices in three made-up tiers
(phones, laptops, workstations), each tier a range of speeds, per-step env costs, latencies
and link bandwidths, drawn from a fixed seed; a faster tier gets bigger budgets. It exists to
show the format and to give tests and examples a fixed heterogeneous population.

    .venv/bin/python -m benchmarks.device_trace          # rewrites docs/device-trace.csv
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

SEED = 17
NUM_DEVICES = 20
# tier: (share of devices, speed range, step delay range in s, latency range in s,
#        bandwidth range in Mbit/s, batch sizes, local iterations)
TIERS = {
    "phone": (0.5, (0.2, 0.6), (2e-4, 8e-4), (0.02, 0.08), (5.0, 30.0), [4, 8], [1, 2]),
    "laptop": (0.35, (0.6, 1.5), (5e-5, 2e-4), (0.005, 0.02), (30.0, 200.0), [8, 16], [2, 3]),
    "workstation": (0.15, (1.5, 4.0), (0.0, 5e-5), (0.001, 0.005), (200.0, 1000.0), [16, 32], [3]),
}
HEADER = "agent,batch_size,local_iters,speed,step_delay_s,latency_s,bandwidth_mbps"


def rows(seed: int = SEED, count: int = NUM_DEVICES) -> list[str]:
    rng = np.random.default_rng(seed)
    names = list(TIERS)
    shares = np.array([TIERS[name][0] for name in names])
    lines = []
    for agent in range(count):
        tier = TIERS[names[int(rng.choice(len(names), p=shares / shares.sum()))]]
        _, speed, delay, latency, bandwidth, batches, iters = tier
        lines.append(
            f"{agent},{rng.choice(batches)},{rng.choice(iters)},"
            f"{rng.uniform(*speed):.3f},{rng.uniform(*delay):.6f},"
            f"{rng.uniform(*latency):.4f},{rng.uniform(*bandwidth):.1f}"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/device-trace.csv"))
    args = parser.parse_args()
    provenance = [
        "# A device population trace for agents.population.kind=trace (README, Populations).",
        "# SYNTHETIC, not measured: written by benchmarks/device_trace.py (seed 17) from three",
        "# made-up tiers (phone, laptop, workstation). Row i is agent i; agents past the last",
        "# row wrap around (agent k takes row k mod 20).",
    ]
    args.out.write_text("\n".join([*provenance, HEADER, *rows()]) + "\n", encoding="utf-8")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logger.info("wrote %s (%d devices)", args.out, NUM_DEVICES)


if __name__ == "__main__":
    main()
