"""Where a round's wall time goes, across the server and its agent hosts.

A real ``fedhpg-run`` federation on loopback (CartPole population, counted clock, two agent
hosts by default) held at θ̃_0 (server step 1e-7: every round samples episodes of the same
length, so rounds are comparable), with ``FEDHPG_TIMELINE=1``: every process marks its
round's phases (:mod:`fedhpg.common.runtime.timeline`). Printed: each phase's time from
the round's start, median over the rounds after the first, and the two figures that
bound the round beside the hosts' own work: how far apart the first and the last host end
their training, and what follows the last host's training until θ̃ is aggregated.

    python -m benchmarks.timeline [--agents 1000 --per-host 500 --rounds 30] [override ...]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from collections import defaultdict
from pathlib import Path

from benchmarks.runtime import _federation

PHASES = [
    ("train-sent", "requests sent"),
    ("first-trained", "first host's training done"),
    ("last-trained", "last host's training done"),
    ("last-answers-sent", "last host's answers sent"),
    ("last-batch", "last answer batch read"),
    ("train-collected", "every answer filed"),
    ("answers-in", "the round's updates built"),
    ("aggregated", "θ̃ aggregated (round time)"),
    ("next-start", "the next round starts"),
    ("recording", "(the round before's record started)"),
    ("recorded", "(the round before's record written)"),
]


def parse(stderr: str) -> dict[int, dict[str, float]]:
    """Each round's phases, seconds from its start."""
    marks: dict[int, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for line in stderr.splitlines():
        _, found, text = line.partition("fedhpg.timeline: ")
        if not found:
            continue
        stamp, who, event, round_index = text.split()
        key = event if who == "server" else f"host-{event}"
        marks[int(round_index)][key].append(float(stamp))
    rounds: dict[int, dict[str, float]] = {}
    for number, seen in marks.items():
        if "round-start" not in seen or "aggregated" not in seen:
            continue
        start = seen["round-start"][0]
        trained = seen.get("host-trained", [])
        sent = seen.get("host-answers-sent", [])
        phases = {
            "train-sent": seen["train-sent"][0],
            "first-trained": min(trained, default=float("nan")),
            "last-trained": max(trained, default=float("nan")),
            "last-answers-sent": max(sent, default=float("nan")),
            "last-batch": max(seen.get("batch", []), default=float("nan")),
            "train-collected": seen["train-collected"][0],
            "answers-in": seen["answers-in"][0],
            "aggregated": seen["aggregated"][0],
        }
        rounds[number] = {key: value - start for key, value in phases.items()}
        # the round before's record (metrics, checkpoint) is written while this round trains
        for mark in ("recording", "recorded"):
            before = marks.get(number - 1, {}).get(mark)
            if before:
                rounds[number][mark] = before[0] - start
        following = marks.get(number + 1, {}).get("round-start")
        if following:
            rounds[number]["next-start"] = following[0] - start
    return rounds


def held_at_start(agents: int, per_host: int, rounds: int) -> list[str]:
    """The overrides of a CartPole population federation on agent hosts whose rounds stay at
    θ̃_0 (server step 1e-7), so that they are comparable; no evaluation."""
    return [
        "env=cartpole", "agents=population", f"agents.num_agents={agents}",
        f"agents.per_host={per_host}", "agents.clock=counted", f"rounds={rounds}",
        f"eval.every={rounds + 1}", "eval.episodes=1", "strategy.params.step_size=1e-7",
        "server.register_timeout_s=600",
    ]  # fmt: skip


def measure(agents: int, per_host: int, rounds: int, extra: list[str]) -> dict[int, dict]:
    overrides = [*held_at_start(agents, per_host, rounds), *extra]
    with tempfile.TemporaryDirectory() as tmp:
        _federation(overrides, Path(tmp), env={"FEDHPG_TIMELINE": "1"})
        return parse((Path(tmp) / "fedhpg-run.stderr").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--per-host", type=int, default=500)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("extra", nargs="*", help="more overrides (key=value)")
    args = parser.parse_args()
    timeline = measure(args.agents, args.per_host, args.rounds, args.extra)
    steady = [timeline[k] for k in sorted(timeline) if k > 1]
    if not steady:
        raise SystemExit("error: no round after the first was marked")
    print(f"{len(steady)} rounds (2–{args.rounds}), ms from the round's start, median [min–max]:")
    for key, label in PHASES:
        values = [1e3 * r[key] for r in steady if key in r]
        if not values:
            continue
        print(f"  {label:32s} {statistics.median(values):7.1f} "
              f"[{min(values):.1f}–{max(values):.1f}]")  # fmt: skip
    spread = [1e3 * (r["last-trained"] - r["first-trained"]) for r in steady]
    after = [1e3 * (r["aggregated"] - r["last-trained"]) for r in steady]
    print(f"  the hosts' training ends apart by {statistics.median(spread):.1f} ms (median); "
          f"from the last host's training to θ̃: {statistics.median(after):.1f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
