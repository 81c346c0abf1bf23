"""The containers' timings as a result table: ``make bench-containers`` (tests/test_containers.py
with ``FEDHPG_CONTAINER_TIMINGS``) measures them from nothing into
``benchmarks/results/containers.json``; this writes ``benchmarks/results/tables/containers.json``
from that file.

    python -m benchmarks.containers                 # make bench-containers, then the table
    python -m benchmarks.containers --tables-only   # the table from the stored timings alone

``--tables-only`` keeps the date, commit and machine of the stored table (the timings file
records none), so the table is the stored measurement's, rendered again.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmarks import results_file

RESULTS = Path("benchmarks/results/containers.json")
ROUNDS = 60
"""The demo's rounds that ``make bench-containers`` times (``FEDHPG_CONTAINER_ROUNDS``)."""


def table(timings: dict[str, Any]) -> str:
    """Each timed phase; a phase the file does not hold is left out."""
    rounds = timings["rounds"]
    phases = [
        ("base_build_s", "base image: `debootstrap --variant=minbase` bookworm + `docker import`",
         0),
        ("wheelhouse_s", "wheelhouse of the pinned dependencies", 0),
        ("image_build_s", "image: `docker build --network none`, two stages"
         + (f" ({timings['image_mb']:,} MB)" if "image_mb" in timings else ""), 0),
        ("compose_up_to_round_1_s", "`docker compose up -d` to the end of round 1", 1),
        ("compose_run_s", f"the demo's {rounds} rounds in containers", 1),
        ("loopback_run_s", f"the same {rounds} rounds with `fedhpg-run` on loopback", 1),
    ]  # fmt: skip
    lines = ["| phase | wall time |", "|---|---|"]
    for key, phase, digits in phases:
        if key in timings:
            lines.append(f"| {phase} | {timings[key]:,.{digits}f} s |")
    return "\n".join(lines)


def summary(timings: dict[str, Any]) -> str:
    """The image's time from nothing and the containers' rounds against loopback's."""
    build = [timings[k] for k in ("base_build_s", "wheelhouse_s", "image_build_s") if k in timings]
    parts = []
    if build:
        parts.append(
            f"An image from nothing (base, wheelhouse, image) takes {sum(build):,.0f} s, "
            f"about {sum(build) / 60:.0f} minutes"
        )
    if "compose_run_s" in timings and "loopback_run_s" in timings:
        ratio = timings["compose_run_s"] / timings["loopback_run_s"]
        parts.append(f"the demo's rounds in containers take {ratio:.2f}× as long as on loopback")
    return ("; ".join(parts) or "No timing stored") + "."


def tables(timings: dict[str, Any]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(table(timings), summary(timings))]


def measure() -> None:
    """What ``make bench-containers`` runs: the cold build and the demo's rounds, timed."""
    env = {
        **os.environ,
        "FEDHPG_CONTAINER_TESTS": "1",
        "FEDHPG_CONTAINER_COLD": "1",
        "FEDHPG_CONTAINER_ROUNDS": str(ROUNDS),
        "FEDHPG_CONTAINER_TIMINGS": str(RESULTS),
    }
    command = [sys.executable, "-m", "pytest", "-q", "-rs", "tests/test_containers.py",
               "-k", "equals_loopback"]  # fmt: skip
    subprocess.run(command, env=env, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help=f"only the table from {RESULTS}, stamped with the stored measurement",
    )
    args = parser.parse_args()
    if not args.tables_only:
        measure()
    timings = json.loads(RESULTS.read_text())
    print(table(timings))
    if args.tables_only:
        results_file.rerender("containers", tables(timings))
    else:
        command = results_file.command_line("benchmarks.containers")
        results_file.refresh("containers", tables(timings), command)


if __name__ == "__main__":
    main()
