"""``make bench``: every benchmark, printed as the markdown tables of BENCHMARKS.md."""

from __future__ import annotations

import platform
import sys
import time

import numpy as np
import torch

from benchmarks import curve, gridworld_threshold, runtime, sampler


def main() -> None:
    torch.set_num_threads(1)
    out = sys.stdout
    out.write(
        f"# fedhpg benchmarks — {time.strftime('%Y-%m-%d %H:%M')}, {platform.machine()}, "
        f"Python {platform.python_version()}, numpy {np.__version__}, torch {torch.__version__}\n\n"
    )
    out.write("## Sampler throughput (python -m benchmarks.sampler)\n\n")
    out.write(sampler.table(sampler.run()) + "\n\n")
    out.write(sampler.gym_table(sampler.run_gym()) + "\n\n")
    out.flush()
    out.write("## Coordination overhead per round (python -m benchmarks.runtime)\n\n")
    results = [runtime.coordination_overhead(k, n) for k in (2, 8) for n in (10_000, 1_000_000)]
    out.write(runtime.table(results) + "\n\n")
    startup, memory = runtime.startup_and_memory(8)
    out.write(
        f"Start-up, `fedhpg-run` to the end of round 1 with K=8: {startup:.2f} s. "
        "Peak memory of the whole federation (PSS summed over its 10 processes): "
        f"{memory:.0f} MiB.\n\n"
    )
    out.flush()
    out.write("## CURVE encryption per message (python -m benchmarks.curve)\n\n")
    out.write(curve.table([(size, *curve.measure(size)) for size in curve.SIZES]) + "\n\n")
    out.flush()
    out.write(
        "## GridWorld: trajectories to solve every environment "
        "(python -m benchmarks.gridworld_threshold)\n\n"
    )
    out.write(gridworld_threshold.table(gridworld_threshold.run()) + "\n")


if __name__ == "__main__":
    main()
