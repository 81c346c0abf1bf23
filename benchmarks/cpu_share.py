"""How much of the machine a federation's round uses: CPU per round of each process.

A real ``fedhpg-run`` federation on loopback (CartPole population, counted clock, two agent
hosts by default) held at θ̃_0 (server step 1e-7: rounds of the same length). After
``--skip`` rounds, each process's CPU time (user + system, every thread, from
``/proc/<pid>/stat``) is read twice, ``--window`` seconds apart; printed: the rounds in the
window, each process's CPU per round, and the share of the machine's cores they used
together. Where that share is near 100 %, the round is bound by CPU work, and moving work
between the hosts cannot shorten it by more than the idle rest.

    python -m benchmarks.cpu_share [--agents 1000 --per-host 500 --window 8] [override ...]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
import time
from pathlib import Path

from benchmarks.runtime import BIN, _children
from benchmarks.timeline import held_at_start

TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime


def _rounds(metrics: Path) -> int:
    return len(metrics.read_text().splitlines()) if metrics.exists() else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--per-host", type=int, default=500)
    parser.add_argument("--skip", type=int, default=20, help="rounds before the window")
    parser.add_argument("--window", type=float, default=8.0, help="seconds measured")
    parser.add_argument("extra", nargs="*", help="more overrides (key=value)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        overrides = [
            *held_at_start(args.agents, args.per_host, rounds=100_000),
            f"server.out_dir={out}", f"hydra.run.dir={out / 'hydra'}", *args.extra,
        ]  # fmt: skip
        with (out / "stderr").open("w") as stderr:
            process = subprocess.Popen(
                [str(BIN / "fedhpg-run"), *overrides],
                stdout=subprocess.DEVNULL,
                stderr=stderr,
                env={**os.environ, "OMP_NUM_THREADS": "1"},
            )
            try:
                metrics = out / "metrics.jsonl"
                deadline = time.monotonic() + 300
                while _rounds(metrics) < args.skip:
                    if process.poll() is not None or time.monotonic() > deadline:
                        stderr.flush()
                        tail = (out / "stderr").read_text().strip().splitlines()[-1:]
                        raise SystemExit(f"error: the federation ended or stalled: {tail}")
                    time.sleep(0.05)
                pids = [process.pid, *_children(process.pid)]
                rounds_before, before = _rounds(metrics), {p: _cpu_s(p) for p in pids}
                started = time.monotonic()
                time.sleep(args.window)
                rounds_after, after = _rounds(metrics), {p: _cpu_s(p) for p in pids}
                elapsed = time.monotonic() - started
            finally:
                process.terminate()
                process.wait(timeout=30)
    rounds = max(rounds_after - rounds_before, 1)
    print(f"{rounds} rounds in {elapsed:.1f} s: {1e3 * elapsed / rounds:.1f} ms a round")
    # the launcher forks the server first, then the hosts
    names = ["launcher", "server", *(f"host {i}" for i in range(len(pids) - 2))]
    for name, pid in zip(names, pids, strict=True):
        used = after[pid] - before[pid]
        share = 100 * used / elapsed
        print(f"  {name:10s} {1e3 * used / rounds:6.1f} ms CPU a round ({share:.0f} %)")
    total = sum(after[p] - before[p] for p in pids)
    cores = os.cpu_count() or 1
    print(f"  together: {100 * total / elapsed:.0f} % of one core, "
          f"{100 * total / elapsed / cores:.0f} % of the machine's {cores}")  # fmt: skip


if __name__ == "__main__":
    main()
