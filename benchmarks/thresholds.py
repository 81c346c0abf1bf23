"""Trajectories per agent to a solved CartPole-v1, K = 10, in FedPG-BR's set-up (H = 500,
γ = 0.999, MLP 16-16, server Adam at 1e-3 and 1e-2): FedPG-BR's own code beside fedhpg's
FedPG-BR, FedHPG with B = 16 and the CartPole presets, every row counted one way.

**Counting.** Trajectories sampled per agent: what the K agents sampled, plus what the server
sampled itself (FedPG-BR's inner loop, b·N_t a round, every batch it drew, those of an inner
step it then aborted included), divided by K. fedhpg's ``trajectories_per_agent`` counts so.
FedPG-BR's code prints another counter, adding round((K·B_t + b·N_t)/(K + 1)) a round without
the aborted step's batch: :func:`counter_step`; :func:`from_counter` converts it.
Evaluation episodes are counted apart, never as trajectories.

**Evaluation.** The greedy return, mean of 10 episodes (one per agent, as FedPG-BR's code
validates 10), after the rounds at which the trajectories per agent cross a multiple of
``INTERVAL`` = 16, the same for every row: every 16/B rounds for a fixed B; every round, then
those rounds kept (:func:`on_grid`), where a round's size varies (FedPG-BR).

**Solved** at t: the greedy return ≥ 475 at every evaluation from t to t + 256 trajectories
per agent (the run must reach t + 256). Beside it: the fraction of evaluations ≥ 475 from
the first one ≥ 475 to the end of the budget (1,000 trajectories per agent), and the last
return. Every run goes to the budget.

fedhpg's rows run in process (``api.run``) on the counted clock, so every count is a
function of the seed. FedPG-BR's own code runs through :mod:`benchmarks.fedpgbr_code` (a
scratch copy, its server's environment seeded), in its own environment.

``python -m benchmarks.thresholds`` runs fedhpg's rows (``--rows``, ``--seeds``,
``--server-lr``; a stored run is kept unless ``--rerun``) and prints the tables from
``benchmarks/results/solved_cartpole.json`` and FedPG-BR's logs in
``benchmarks/results/fedpgbr_code/``. ``--wall --fedpgbr-python P --fedpgbr-code DIR`` runs the
stable preset, fedhpg's FedPG-BR and FedPG-BR's code back to back, seed after seed, each in a
fresh process (the wall-time comparison, and FedPG-BR's code's rows). ``--search`` runs the
preset search on seeds of its own. ``--table-only`` prints the tables and draws
``docs/figures/solved_cartpole.png`` from what is stored.

Each run writes its result tables (``benchmarks/results/tables/``): ``thresholds`` (the rows,
per seed, FedPG-BR's counter), ``thresholds_search`` (``--search``) and ``thresholds_wall``
(``--wall``). ``--tables-only`` writes all three again from the stored runs alone, stamped with
the date, commit and machine they were measured with.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from benchmarks import results_file

TARGET = 475.0
HOLD = 256.0
"""Trajectories per agent over which every evaluation must be ≥ ``TARGET``."""
INTERVAL = 16
"""Trajectories per agent between evaluations, every row."""
BUDGET = 1000
"""Trajectories per agent every run goes to."""
AGENTS = 10
MINI_BATCH = 4
"""b, the trajectories of one of FedPG-BR's server inner steps (its code's and fedhpg's)."""
EVAL_EPISODES = 10
"""Greedy episodes per evaluation: one per agent (FedPG-BR's code validates 10)."""
STEPS = (0.001, 0.01)
SEEDS = (0, 1, 2, 3, 4)
RESULTS = Path("benchmarks/results/solved_cartpole.json")
CODE_LOGS = Path("benchmarks/results/fedpgbr_code")
FIGURE = Path("docs/figures/solved_cartpole.png")
COMMON = ("agents.clock=counted", "agents.step_delays_s=[0]", "eval.episodes=1")
SEARCH_SEEDS = (100, 101, 102, 103, 104)
"""The seeds the stable preset was chosen on (``--search``), none of the table's."""
SEARCH_RESULTS = Path("benchmarks/results/solved_cartpole_search.json")
SEARCH_FIGURE = Path("docs/figures/solved_cartpole_search.png")


@dataclass(frozen=True)
class Row:
    label: str
    overrides: tuple[str, ...]
    """fedhpg's overrides (none for FedPG-BR's own code)."""
    per_round: int | None
    """Trajectories per agent a round, where fixed (None: a round's size varies)."""


ROWS: dict[str, Row] = {
    "fedpgbr_code": Row("FedPG-BR, its own code", (), None),
    "fedpgbr": Row(
        "FedPG-BR (fedhpg's)",
        ("experiment=k10_cartpole", "algo=fedpgbr", "strategy=fedpgbr"),
        None,
    ),
    "fedhpg": Row("FedHPG, B = 16 (`k10_cartpole`)", ("experiment=k10_cartpole",), 16),
    "tuned": Row("B = 1 (`k10_cartpole_tuned`)", ("experiment=k10_cartpole_tuned",), 1),
    "stable": Row("B = 2 (`k10_cartpole_stable`)", ("experiment=k10_cartpole_stable",), 2),
    "b4": Row("B = 4", ("experiment=k10_cartpole", "agents.budget.batch_size=[4]"), 4),
}
TABLE_ROWS = ("fedpgbr_code", "fedpgbr", "fedhpg", "tuned", "stable")
SEARCH_ROWS = ("tuned", "stable", "b4")


# --- FedPG-BR's counter ---------------------------------------------------------------------


def counter_step(
    batch_size: int, inner_steps: int, agents: int = AGENTS, mini_batch: int = MINI_BATCH
) -> int:
    """What FedPG-BR's code adds to the counter it prints after a round (K > 1): B_t for each
    of the K agents and b·N_t for its server, N_t the inner steps it took (an aborted step's
    batch left out), spread over K + 1 and rounded (Python's round, half to even)."""
    return round((agents * batch_size + mini_batch * inner_steps) / (agents + 1))


def sampled_per_agent(
    batch_size: int, inner_batches: int, agents: int = AGENTS, mini_batch: int = MINI_BATCH
) -> float:
    """Trajectories per agent a FedPG-BR round sampled: B_t, plus the server's b per batch it
    drew (an aborted step's included) divided by K."""
    return batch_size + mini_batch * inner_batches / agents


def from_counter(counter: float, agents: int = AGENTS) -> float:
    """Trajectories per agent from FedPG-BR's printed counter alone: counter · (K + 1)/K.
    Low by b/K for every aborted inner step, and off by its rounding, at most (K + 1)/(2K) a
    round (tests/test_thresholds.py checks both against a logged run)."""
    return counter * (agents + 1) / agents


# --- curves ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Curve:
    """Every evaluation of one run, in order."""

    row: str
    server_lr: float
    seed: int
    trajectories: list[float]
    """Trajectories per agent when evaluated."""
    returns: list[float]
    rounds: list[int]
    wall_s: list[float]
    """Seconds since the run was started (its set-up included) when evaluated."""


@dataclass(frozen=True)
class Outcome:
    """What the rules make of one curve."""

    first: float | None
    solved: float | None
    held: float | None
    """Fraction of evaluations ≥ TARGET from the first one ≥ TARGET on."""
    last: float
    rounds: int | None
    """Rounds to solved."""
    episodes: int | None
    """Evaluation episodes the run had spent when solved (every evaluation it made)."""
    wall_s: float | None
    """Seconds to solved."""
    first_wall_s: float | None
    """Seconds to the first evaluation ≥ TARGET."""
    end_wall_s: float
    """Seconds to the end of the budget."""


def on_grid(curve: Curve, interval: float = INTERVAL) -> list[int]:
    """Indices of the evaluations after which the trajectories per agent crossed a multiple of
    ``interval`` since the evaluation before (all of them for a fixed B at interval/B rounds)."""
    kept, before = [], 0.0
    for i, t in enumerate(curve.trajectories):
        if math.floor(t / interval + 1e-9) > math.floor(before / interval + 1e-9):
            kept.append(i)
        before = t
    return kept


def outcome(curve: Curve, interval: float = INTERVAL, hold: float = HOLD) -> Outcome:
    grid = on_grid(curve, interval)
    t = [curve.trajectories[i] for i in grid]
    r = [curve.returns[i] for i in grid]
    first = next((j for j, value in enumerate(r) if value >= TARGET), None)
    solved = None
    for j in range(len(r)):
        if t[j] + hold > curve.trajectories[-1]:
            break  # the run ends before the hold would
        window = [value for time_, value in zip(t[j:], r[j:], strict=True) if time_ <= t[j] + hold]
        if all(value >= TARGET for value in window):
            solved = j
            break
    held = None if first is None else sum(v >= TARGET for v in r[first:]) / len(r[first:])
    at = None if solved is None else grid[solved]
    return Outcome(
        first=None if first is None else t[first],
        solved=None if solved is None else t[solved],
        held=held,
        last=curve.returns[-1],
        rounds=None if at is None else curve.rounds[at],
        episodes=None if at is None else (at + 1) * EVAL_EPISODES,
        wall_s=None if at is None else curve.wall_s[at],
        first_wall_s=None if first is None else curve.wall_s[grid[first]],
        end_wall_s=curve.wall_s[-1],
    )


class _Stop(Exception):
    """Raised from the round callback once the budget is spent."""


def run_curve(row: str, server_lr: float, seed: int, budget: int = BUDGET) -> Curve:
    """One of fedhpg's rows to ``budget`` trajectories per agent."""
    from fedhpg.server.commands import api

    spec = ROWS[row]
    trajectories: list[float] = []
    returns: list[float] = []
    rounds: list[int] = []
    wall: list[float] = []
    started = time.perf_counter()

    def watch(record: Any, theta: Any) -> None:
        if record.eval is not None:
            trajectories.append(record.trajectories_per_agent)
            returns.append(statistics.mean(e.return_mean for e in record.eval.values()))
            rounds.append(record.round)
            wall.append(time.perf_counter() - started)
            if record.trajectories_per_agent >= budget:
                raise _Stop

    if spec.per_round is None:  # evaluated every round, kept on the grid (on_grid)
        schedule = ["eval.every=1", f"rounds={budget}"]
    else:
        every = INTERVAL // spec.per_round
        schedule = [f"eval.every={every}", f"rounds={math.ceil(budget / spec.per_round)}"]
    overrides = [
        *spec.overrides,
        *COMMON,
        *schedule,
        f"strategy.params.step_size={server_lr}",
        f"seed={seed}",
    ]
    with contextlib.suppress(_Stop):
        api.run(overrides=overrides, callbacks=[watch])
    return Curve(row, server_lr, seed, trajectories, returns, rounds, wall)


def code_curve(log: Path) -> Curve:
    """FedPG-BR's code's run from its :mod:`benchmarks.fedpgbr_code` log, counted here."""
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    header, rounds = lines[0], lines[1:]
    agents, mini_batch = header["K"], header["b"]
    per_agent, trajectories = 0.0, []
    for line in rounds:
        per_agent += sampled_per_agent(
            line["batch_size"], line["inner_batches"], agents, mini_batch
        )
        trajectories.append(per_agent)
    return Curve(
        "fedpgbr_code",
        header["server_lr"],
        header["seed"],
        trajectories,
        [line["return"] for line in rounds],
        [line["round"] for line in rounds],
        [line["wall_s"] for line in rounds],
    )


def code_log(server_lr: float, seed: int, folder: Path = CODE_LOGS) -> Path:
    return folder / f"lr{server_lr:g}_seed{seed}.jsonl"


def load(path: Path = RESULTS, folder: Path | None = CODE_LOGS) -> list[Curve]:
    """fedhpg's stored curves, and FedPG-BR's code's from its logs in ``folder``."""
    curves = [Curve(**c) for c in json.loads(path.read_text())] if path.exists() else []
    logs = sorted(folder.glob("*.jsonl")) if folder is not None else []
    return curves + [code_curve(log) for log in logs]


def save(curves: list[Curve], path: Path = RESULTS) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ours = [asdict(c) for c in curves if c.row != "fedpgbr_code"]
    path.write_text(json.dumps(ours, indent=0) + "\n")


def replace(curves: list[Curve], new: Curve) -> list[Curve]:
    key = (new.row, new.server_lr, new.seed)
    return [c for c in curves if (c.row, c.server_lr, c.seed) != key] + [new]


# --- tables and figure ----------------------------------------------------------------------


def _spread(values: Sequence[float | None], digits: int = 0) -> str:
    hits = [v for v in values if v is not None]
    if not hits:
        return "never"
    text = (
        f"{statistics.median(hits):,.{digits}f} ({min(hits):,.{digits}f}–{max(hits):,.{digits}f})"
    )
    missed = len(values) - len(hits)
    return text + (f", {missed} of {len(values)} never" if missed else "")


def _percent(values: Sequence[float | None]) -> str:
    hits = [v for v in values if v is not None]
    if not hits:
        return "—"
    return f"{100 * statistics.median(hits):.0f} % (lowest {100 * min(hits):.0f} %)"


def table(curves: list[Curve], rows: Sequence[str] = TABLE_ROWS) -> str:
    lines = [
        "| run | server step | seeds solved | trajectories/agent to solved, median (range) "
        f"| to the first ≥ {TARGET:g} | evaluations ≥ {TARGET:g} after the first, median "
        f"(lowest) | last return, median (lowest) | rounds to solved (messages) | evaluation "
        "episodes to solved |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for lr in sorted({c.server_lr for c in curves}):
        for row in rows:
            group = sorted(
                (c for c in curves if (c.row, c.server_lr) == (row, lr)), key=lambda c: c.seed
            )
            if not group:
                continue
            found = [outcome(c) for c in group]
            solved = [o.solved for o in found]
            rounds = [o.rounds for o in found if o.rounds is not None]
            messages = (
                f"{statistics.median(rounds):,.0f} ({2 * AGENTS * statistics.median(rounds):,.0f})"
                if rounds
                else "—"
            )
            lasts = [o.last for o in found]
            lines.append(
                f"| {ROWS[row].label} | {lr:g} | {len(rounds)}/{len(group)} | {_spread(solved)} "
                f"| {_spread([o.first for o in found])} | {_percent([o.held for o in found])} "
                f"| {statistics.median(lasts):.0f} ({min(lasts):.0f}) | {messages} "
                f"| {_spread([o.episodes for o in found])} |"
            )
    return "\n".join(lines)


def per_seed(curves: list[Curve], rows: Sequence[str] = TABLE_ROWS) -> str:
    lines = [
        "| run | server step | per seed: solved at / evaluations ≥ 475 after the first / last "
        "return |",
        "|---|---|---|",
    ]
    for lr in sorted({c.server_lr for c in curves}):
        for row in rows:
            group = sorted(
                (c for c in curves if (c.row, c.server_lr) == (row, lr)), key=lambda c: c.seed
            )
            if not group:
                continue
            cells = []
            for c in group:
                o = outcome(c)
                solved = "never" if o.solved is None else f"{o.solved:,.0f}"
                held = "—" if o.held is None else f"{100 * o.held:.0f} %"
                cells.append(f"{c.seed}: {solved} / {held} / {o.last:.0f}")
            lines.append(f"| {ROWS[row].label} | {lr:g} | {'; '.join(cells)} |")
    return "\n".join(lines)


def _seconds(value: float | None) -> str:
    return "never" if value is None else f"{value:.1f}"


def _ratio(theirs: float | None, ours: float | None) -> str:
    return "—" if theirs is None or ours is None else f"{theirs / ours:.0f}×"


TIMED = ("stable", "fedpgbr", "fedpgbr_code")
"""The rows ``--wall`` times back to back: the B = 2 preset, fedhpg's FedPG-BR, its own code."""


def timed_runs(curves: list[Curve]) -> list[tuple[float, int, dict[str, Outcome]]]:
    """(server step, seed, each timed row's outcome) for every step and seed with all three."""
    found_all = []
    for lr in sorted({c.server_lr for c in curves}):
        for seed in sorted({c.seed for c in curves if c.row == "fedpgbr_code"}):
            found = {}
            for row in TIMED:
                match = [c for c in curves if (c.row, c.server_lr, c.seed) == (row, lr, seed)]
                if match:
                    found[row] = outcome(match[0])
            if len(found) == len(TIMED):
                found_all.append((lr, seed, found))
    return found_all


def wall_table(curves: list[Curve]) -> str:
    """Seconds to solved and to the budget of the runs timed back to back (``--wall``)."""
    lines = [
        "| server step | seed | B = 2 preset: first ≥ 475 / solved / whole run (s) "
        "| fedhpg's FedPG-BR | FedPG-BR's code | FedPG-BR's code over the preset: to the first "
        "≥ 475 / to solved / whole run |",
        "|---|---|---|---|---|---|",
    ]
    for lr, seed, found in timed_runs(curves):
        cells = [
            f"{_seconds(o.first_wall_s)} / {_seconds(o.wall_s)} / {o.end_wall_s:.1f}"
            for o in (found[row] for row in TIMED)
        ]
        ours, theirs = found["stable"], found["fedpgbr_code"]
        ratios = [
            _ratio(theirs.first_wall_s, ours.first_wall_s),
            _ratio(theirs.wall_s, ours.wall_s),
            _ratio(theirs.end_wall_s, ours.end_wall_s),
        ]
        lines.append(f"| {lr:g} | {seed} | {' | '.join(cells)} | {' / '.join(ratios)} |")
    return "\n".join(lines)


def wall_summary(curves: list[Curve]) -> str:
    """The B = 2 preset's seconds to solved and FedPG-BR's code's ratios to it, over the
    seeds and steps timed."""
    runs = [found for _, _, found in timed_runs(curves)]
    if not runs:
        return "No run timed."
    solved = [f["stable"].wall_s for f in runs]
    first = [
        theirs / ours
        for f in runs
        if (theirs := f["fedpgbr_code"].first_wall_s) is not None
        and (ours := f["stable"].first_wall_s) is not None
    ]
    whole = [f["fedpgbr_code"].end_wall_s / f["stable"].end_wall_s for f in runs]
    hits = [v for v in solved if v is not None]
    text = "Across seeds the B = 2 preset is solved in " + (
        f"{min(hits):.1f}–{max(hits):.1f} s" if hits else "no run"
    )
    if len(hits) < len(solved):
        text += f" ({len(solved) - len(hits)} of {len(solved)} runs never)"
    if first:
        text += (
            f"; FedPG-BR's code reaches its first {TARGET:g} {min(first):.0f}–{max(first):.0f}× "
            "later"
        )
    return text + f" and takes {min(whole):.0f}–{max(whole):.0f}× the preset's whole run."


@dataclass(frozen=True)
class Conversion:
    """One logged run of FedPG-BR's code at its end: its printed counter and what it sampled."""

    server_lr: float
    seed: int
    rounds: int
    aborted: int
    """Rounds with an aborted inner step."""
    counter: int
    converted: float
    """:func:`from_counter` of the counter."""
    sampled: float
    """Trajectories per agent counted from the log."""


def conversions(folder: Path = CODE_LOGS) -> list[Conversion]:
    found = []
    for log in sorted(folder.glob("*.jsonl")):
        rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
        header, rounds = rows[0], rows[1:]
        counter = rounds[-1]["counter"]
        found.append(
            Conversion(
                server_lr=header["server_lr"],
                seed=header["seed"],
                rounds=len(rounds),
                aborted=sum(r["inner_batches"] > r["inner_steps"] for r in rounds),
                counter=counter,
                converted=from_counter(counter, header["K"]),
                sampled=code_curve(log).trajectories[-1],
            )
        )
    return found


def conversion_table(folder: Path = CODE_LOGS) -> str:
    """FedPG-BR's printed counter at each run's end beside the trajectories per agent counted
    from its log, and :func:`from_counter`'s reading of it."""
    lines = [
        "| server step | seed | rounds | rounds with an aborted inner step | printed counter "
        "| counter · 11/10 | trajectories per agent sampled |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in conversions(folder):
        lines.append(
            f"| {c.server_lr:g} | {c.seed} | {c.rounds} | {c.aborted} | {c.counter:,} "
            f"| {c.converted:,.1f} | {c.sampled:,.1f} |"
        )
    return "\n".join(lines)


def conversion_summary(folder: Path = CODE_LOGS) -> str:
    """How far the converted counter is from what the runs sampled, and on which side."""
    found = conversions(folder)
    if not found:
        return "No logged run."
    gaps = [c.sampled - c.converted for c in found]
    low = sum(g > 0 for g in gaps)
    return (
        f"Its counter · 11/10 is within {max(abs(g) for g in gaps):.1f} trajectories per agent "
        f"of what its runs sampled, below it in {low} of {len(found)} runs: it leaves out the "
        f"batches of aborted inner steps (b/K = {MINI_BATCH / AGENTS:g} each) and is rounded "
        "every round."
    )


def _outcomes(curves: list[Curve], row: str, lr: float) -> list[Outcome]:
    group = sorted((c for c in curves if (c.row, c.server_lr) == (row, lr)), key=lambda c: c.seed)
    return [outcome(c) for c in group]


def _reached(values: Sequence[float | None]) -> list[float]:
    """``values`` where none is missing (every seed reached), else none."""
    return [v for v in values if v is not None] if None not in values else []


def _short(row: str) -> str:
    return ROWS[row].label.split(" (")[0]


def _steps(curves: list[Curve]) -> list[float]:
    return sorted({c.server_lr for c in curves})


def _step_names(steps: Sequence[float], every: Sequence[float]) -> str:
    if len(steps) == len(every) > 1:
        return "both steps" if len(every) == 2 else "every step"
    return " and ".join(f"{lr:g}" for lr in steps)


def summary(curves: list[Curve], rows: Sequence[str]) -> str:
    """What the main table says, from the runs: at which steps the B = 2 preset is solved
    before FedPG-BR's own code on every seed and whether it stays solved, which rows never
    reach the target within the budget, and which row reaches a first one soonest at each
    step, with how well it holds it."""
    steps = _steps(curves)
    sentences = []
    stable = f"{_short('stable')} preset (`{ROWS['stable'].overrides[0]}`)"
    if "stable" in rows and "fedpgbr_code" in rows:
        sooner = []
        for lr in steps:
            ours, theirs = _outcomes(curves, "stable", lr), _outcomes(curves, "fedpgbr_code", lr)
            if (
                ours
                and len(ours) == len(theirs)
                and all(
                    o.solved is not None and (t.solved is None or o.solved < t.solved)
                    for o, t in zip(ours, theirs, strict=True)
                )
            ):
                sooner.append(lr)
        held = [o.held for lr in steps for o in _outcomes(curves, "stable", lr)]
        if sooner:
            text = (
                f"The {stable} is solved sooner than FedPG-BR's own code on every seed "
                f"at {_step_names(sooner, steps)}"
            )
            if all(h == 1.0 for h in held):
                text += f", and stays solved (every evaluation ≥ {TARGET:g} after its first)"
            sentences.append(text + ".")
    never = [
        f"{ROWS[row].label} does not reach {TARGET:g} within {BUDGET:,} at {lr:g}"
        for row in rows
        for lr in steps
        if (found := _outcomes(curves, row, lr)) and all(o.first is None for o in found)
    ]
    if never:
        sentences.append("; ".join(never) + ".")
    soonest = []
    for lr in steps:
        firsts: dict[str, float] = {}
        for row in rows:
            reached = _reached([o.first for o in _outcomes(curves, row, lr)])
            if reached:
                firsts[row] = statistics.median(reached)
        if firsts:
            row = min(firsts, key=lambda r: firsts[r])
            found = _outcomes(curves, row, lr)
            held_median = statistics.median(_reached([o.held for o in found]))
            solved = sum(o.solved is not None for o in found)
            soonest.append(
                f"at {lr:g} {ROWS[row].label} ({firsts[row]:,.0f} at the median), solved on "
                f"{solved} of {len(found)} seeds, {100 * held_median:.0f} % of its evaluations "
                "after the first at the median"
            )
    if soonest:
        sentences.append(f"First ≥ {TARGET:g} soonest: " + "; ".join(soonest) + ".")
    return " ".join(sentences) or "No run stored."


PER_SEED_SUMMARY = (
    "Each seed's solved point, the share of evaluations ≥ {target:g} after the first, and the "
    "return at {budget:,} trajectories per agent."
)


def search_summary(curves: list[Curve], rows: Sequence[str]) -> str:
    """For each searched row beside the B = 2 preset: on how many seeds it is solved at each
    step where it is not on all, else its trajectories to solved against the preset's."""
    steps = _steps(curves)
    sentences = []
    for row in rows:
        if row == "stable":
            continue
        counts = {lr: _outcomes(curves, row, lr) for lr in steps}
        short = [
            f"{sum(o.solved is not None for o in found)} of {len(found)} seeds at {lr:g}"
            for lr, found in counts.items()
            if found and any(o.solved is None for o in found)
        ]
        if short:
            sentences.append(f"{_short(row)} is not held: solved on {', '.join(short)}")
            continue
        ratios = []
        for lr, found in counts.items():
            ours = _reached([o.solved for o in found])
            base = _reached([o.solved for o in _outcomes(curves, "stable", lr)])
            if ours and base:
                ratios.append(statistics.median(ours) / statistics.median(base))
        if ratios:
            sentences.append(
                f"{_short(row)} is held on every seed but needs {min(ratios):.1f}–"
                f"{max(ratios):.1f}× {_short('stable')}'s trajectories to solved (medians)"
            )
    varied = ", ".join(_short(row) for row in rows)
    return (
        "; ".join(sentences)
        + f". Only B was searched ({varied}): a step-size decay, a larger B later in training, "
        "the planner's B_k and FedHPGVR were not tried."
    )


def main_tables(
    curves: list[Curve], rows: Sequence[str], folder: Path | None
) -> list[results_file.Table]:
    """The ``thresholds`` result: the rows, per seed, and FedPG-BR's counter where its logs
    are stored."""
    tables = [
        results_file.table_from_markdown(table(curves, rows), summary(curves, rows)),
        results_file.table_from_markdown(
            per_seed(curves, rows),
            PER_SEED_SUMMARY.format(target=TARGET, budget=BUDGET),
            title="Per seed",
        ),
    ]
    if folder is not None and conversions(folder):
        tables.append(
            results_file.table_from_markdown(
                conversion_table(folder),
                conversion_summary(folder),
                title="FedPG-BR's printed counter against the trajectories its runs sampled "
                "(the last round of each logged run)",
            )
        )
    return tables


def search_tables(curves: list[Curve], rows: Sequence[str]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(table(curves, rows), search_summary(curves, rows))]


def wall_tables(curves: list[Curve]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(wall_table(curves), wall_summary(curves))]


def stored_rows(curves: list[Curve]) -> list[str]:
    """The rows stored, in the tables' order."""
    rows = [r for r in TABLE_ROWS if any(c.row == r for c in curves)]
    return rows + [r for r in ROWS if r not in rows and any(c.row == r for c in curves)]


def write_tables() -> None:
    """The three result tables again from the stored runs, stamped with their measurement."""
    curves = load(RESULTS, CODE_LOGS)
    results_file.rerender("thresholds", main_tables(curves, stored_rows(curves), CODE_LOGS))
    results_file.rerender("thresholds_wall", wall_tables(curves))
    search = load(SEARCH_RESULTS, None)
    results_file.rerender("thresholds_search", search_tables(search, stored_rows(search)))


def plot(curves: list[Curve], path: Path = FIGURE, rows: Sequence[str] = TABLE_ROWS) -> None:
    """One panel per row and server step: every seed's evaluations (thin) and their mean
    (thick), each seed's curve read at the grid as its last evaluation at or before it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from fedhpg.server.commands.plot import save as save_figure

    steps = sorted({c.server_lr for c in curves})
    figure, axes = plt.subplots(
        len(rows), len(steps), figsize=(4.2 * len(steps), 1.9 * len(rows)), sharex=True,
        sharey=True, squeeze=False,
    )  # fmt: skip
    grid = np.arange(INTERVAL, BUDGET + 1, INTERVAL, dtype=float)
    for i, row in enumerate(rows):
        for j, lr in enumerate(steps):
            axis = axes[i][j]
            group = [c for c in curves if (c.row, c.server_lr) == (row, lr)]
            sampled = []
            for c in group:
                kept = on_grid(c)
                x = np.array([c.trajectories[k] for k in kept])
                y = np.array([c.returns[k] for k in kept])
                axis.plot(x, y, linewidth=0.7, alpha=0.55)
                at = np.searchsorted(x, grid + 1e-9, side="right") - 1
                sampled.append(np.where(at >= 0, y[np.clip(at, 0, None)], np.nan))
            if sampled:
                with warnings.catch_warnings():  # the grid's points before a run's first
                    warnings.simplefilter("ignore", RuntimeWarning)
                    mean = np.nanmean(sampled, axis=0)
                axis.plot(grid, mean, color="black", linewidth=1.8)
            axis.axhline(TARGET, color="grey", linestyle="--", linewidth=0.8)
            axis.set_xlim(0, BUDGET)
            axis.set_ylim(0, 520)
            if i == 0:
                axis.set_title(f"server Adam step {lr:g}", fontsize="medium")
            if j == 0:
                axis.set_ylabel(ROWS[row].label.replace(" (`", "\n(`").replace("`", ""),
                                fontsize="small")  # fmt: skip
            if i == len(rows) - 1:
                axis.set_xlabel("trajectories per agent")
    figure.suptitle(
        "CartPole-v1, K = 10: greedy return (10 episodes), each seed (thin) and their mean",
        fontsize="medium",
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(figure, path)


# --- back to back: wall time ----------------------------------------------------------------


def _timed(command: list[str], out: Path, environment: dict[str, str] | None = None) -> None:
    result = subprocess.run(command, env=environment, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
    if not out.exists():
        raise RuntimeError(f"{' '.join(command)} wrote no {out}")


def wall(
    seeds: Sequence[int],
    steps: Sequence[float],
    python: Path,
    code: Path,
    curves: list[Curve],
    results: Path,
    folder: Path,
) -> list[Curve]:
    """The stable preset, fedhpg's FedPG-BR and FedPG-BR's code, seed after seed, each in a
    fresh process at this process's priority; FedPG-BR's logs are kept in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for lr in steps:
        for seed in seeds:
            for row in ("stable", "fedpgbr"):
                with tempfile.TemporaryDirectory() as scratch:
                    out = Path(scratch) / "curve.json"
                    _timed(
                        [sys.executable, "-m", "benchmarks.thresholds", "--one", row,
                         "--seeds", str(seed), "--server-lr", str(lr), "--out", str(out)],
                        out,
                    )  # fmt: skip
                    curve = Curve(**json.loads(out.read_text()))
                curves = replace(curves, curve)
                save(curves, results)
                print(f"{row} lr={lr:g} seed {seed}: {outcome(curve)}", flush=True)
            log = code_log(lr, seed, folder)
            _timed(
                [str(python), "-m", "benchmarks.fedpgbr_code", "--code", str(code),
                 "--seed", str(seed), "--server-lr", str(lr), "--budget", str(BUDGET),
                 "--log", str(log)],
                log,
                {**os.environ, "PYTHONPATH": str(Path.cwd())},
            )  # fmt: skip
            print(f"FedPG-BR's code lr={lr:g} seed {seed}: {outcome(code_curve(log))}", flush=True)
    return curves


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--server-lr", type=float, nargs="+", default=list(STEPS))
    fedhpg_rows = [r for r in ROWS if r != "fedpgbr_code"]
    parser.add_argument("--rows", nargs="+", choices=fedhpg_rows, default=fedhpg_rows[:-1])
    parser.add_argument("--rerun", action="store_true", help="rerun the stored runs asked for")
    parser.add_argument("--table-only", action="store_true", help="tables and figure only")
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help="only the result tables from the stored runs, stamped with their measurement",
    )
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--code-logs", type=Path, default=CODE_LOGS)
    parser.add_argument("--figure", type=Path, default=FIGURE)
    parser.add_argument("--wall", action="store_true", help="the back-to-back timing")
    parser.add_argument("--fedpgbr-python", type=Path, help="--wall: its environment's python")
    parser.add_argument("--fedpgbr-code", type=Path, help="--wall: the scratch copy's codes/")
    parser.add_argument(
        "--search",
        action="store_true",
        help=f"the preset search: rows {', '.join(SEARCH_ROWS)} on seeds "
        f"{SEARCH_SEEDS[0]}-{SEARCH_SEEDS[-1]}, kept in {SEARCH_RESULTS}, drawn in {SEARCH_FIGURE}",
    )
    parser.add_argument("--one", choices=fedhpg_rows, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.tables_only:
        write_tables()
        return
    if args.one is not None:  # one run for --wall, in its own process
        curve = run_curve(args.one, args.server_lr[0], args.seeds[0])
        args.out.write_text(json.dumps(asdict(curve)))
        return
    if args.search:
        args.rows, args.seeds = list(SEARCH_ROWS), list(SEARCH_SEEDS)
        args.results, args.figure, args.code_logs = SEARCH_RESULTS, SEARCH_FIGURE, None
    curves = [c for c in load(args.results, args.code_logs) if c.row != "fedpgbr_code"]
    if args.wall:
        if args.fedpgbr_python is None or args.fedpgbr_code is None:
            parser.error("--wall needs --fedpgbr-python and --fedpgbr-code")
        curves = wall(
            args.seeds,
            args.server_lr,
            args.fedpgbr_python,
            args.fedpgbr_code,
            curves,
            args.results,
            args.code_logs or CODE_LOGS,
        )
    ran = bool(args.wall)
    if not args.wall and not args.table_only:
        done = set() if args.rerun else {(c.row, c.server_lr, c.seed) for c in curves}
        for lr in args.server_lr:
            for row in args.rows:
                for seed in args.seeds:
                    if (row, lr, seed) in done:
                        continue
                    curve = run_curve(row, lr, seed)
                    ran = True
                    print(f"{row} lr={lr:g} seed {seed}: {outcome(curve)}", flush=True)
                    curves = replace(curves, curve)
                    save(curves, args.results)
    curves = load(args.results, args.code_logs)
    rows = stored_rows(curves)
    print(table(curves, rows))
    print()
    print(per_seed(curves, rows))
    if any(c.row == "fedpgbr_code" for c in curves):
        print()
        print(wall_table(curves))
        print()
        print(conversion_table(args.code_logs))
    plot(curves, args.figure, rows)
    command = results_file.command_line("benchmarks.thresholds")
    if not ran:  # every run asked for was stored: the tables keep their measurement's stamps
        write_tables()
    elif args.search and args.results == SEARCH_RESULTS:
        results_file.refresh("thresholds_search", search_tables(curves, rows), command)
    elif args.results == RESULTS and not args.search:
        results_file.refresh("thresholds", main_tables(curves, rows, args.code_logs), command)
        if args.wall:
            results_file.refresh("thresholds_wall", wall_tables(curves), command)
    print(f"\nfigure: {args.figure}")


if __name__ == "__main__":
    main()
