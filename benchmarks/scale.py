"""``make bench-scale``: thousands of heterogeneous CartPole agents on agent hosts.

Real ``fedhpg-run`` federations on loopback (server + agent hosts, or one process per agent),
CartPole variants, 16-16 MLP, B_k and τ_k from the shipped population, counted clock. Per case:
start-up to the end of round 1, peak PSS of the whole federation (server, hosts, launcher),
env steps per second while the hosts sample (from the engine's own split of its CPU time,
reported per agent in metrics.jsonl), per second of round wall time (from one round's θ̃ to
the next's), and the server's coordination time per participating agent. The cases at the
targets run :attr:`Case.repeats` times, and each window pools the same rounds of every
run. The two references run in this same process on
the same number of env copies as one host steps: (a) a bare ``gym.make_vec`` CartPole loop,
(b) the same plus one stacked forward and draw of every agent's own MLP per step; each is
measured :data:`REF_REPEATS` times before the federation and as many after it, and the
median is the reference (on a shared machine one measurement wanders by ±30 %; right after a
minute of load on both cores it was once 40 % below its usual figure), the range kept beside
it. Then :mod:`benchmarks.engine_ab` compares this tree's agent groups with the last commit
that had a copy of the algorithm per backend, rounds interleaved: FedHPG at θ̃_0 and at the
K = 1,000 case's final θ̃, FedHPGVR at K = 1,000.

    python -m benchmarks.scale            # all cases, table on stdout, JSON + figure
    python -m benchmarks.scale k1000 device --out FILE   # a subset, its JSON to FILE
    python -m benchmarks.scale k1000 device --rounds 4 --skip-baseline --out FILE  # shorter
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from benchmarks import engine_ab, results_file
from benchmarks.runtime import _federation
from benchmarks.scale_refs import bare_loop, cpu_description, forward_loop
from fedhpg.common.learning.components import agent_profile
from fedhpg.common.runtime.cli import compose
from fedhpg.server.checkpoint import latest_valid_checkpoint

RESULTS = Path(__file__).parent / "results" / "scale.json"
MEASURES = [
    *results_file.RUNTIME_CODE,
    "common/learning/engine",
    "common/learning/batched",
    "common/learning/algorithms",
]
"""What a federation of CartPole agents on the compiled engine runs through."""
FIGURE = Path(__file__).parents[1] / "docs" / "scale.png"
CORES = os.cpu_count() or 1


@dataclass(frozen=True)
class Case:
    name: str
    agents: int
    per_host: int
    per_round: int | None = None
    rounds: int = 4
    hidden: int = 16
    extra: tuple[str, ...] = ()
    cold_cache: bool = False
    """Start with an empty numba cache (the compiled engine compiles its kernels first)."""
    repeats: int = 1
    """Runs of the federation; the throughput windows pool their rounds (a window of three
    early rounds moves by ±20 % between single runs on this shared machine)."""

    def overrides(self) -> list[str]:
        out = [
            "env=cartpole",
            "agents=population",
            f"agents.num_agents={self.agents}",
            f"agents.per_host={self.per_host}",
            "agents.clock=counted",
            f"policy.hidden=[{self.hidden},{self.hidden}]",
            f"rounds={self.rounds}",
            f"eval.every={self.rounds + 1}",
            "eval.episodes=1",
            "server.register_timeout_s=600",
            *self.extra,
        ]
        if self.per_round is not None:
            out += ["strategy.participation.mode=uniform",
                    f"strategy.participation.per_round={self.per_round}"]  # fmt: skip
        return out


@dataclass
class CaseResult:
    case: Case
    start_to_round_1_s: float
    peak_pss_mib: float
    participants: int
    env_steps_per_round: float
    sampling_steps_per_cpu_s: float
    """Env steps per CPU second of the hosts' sampling (engine_sample_s)."""
    round_steps_per_s: float
    """Env steps per second of wall time from one round's θ̃ to the next's, all hosts together:
    the round and whatever the server does between rounds (its record keeping), evaluations
    excluded (:func:`round_walls`)."""
    round_time_s: float
    coordination_us_per_agent: float
    """Median over rounds of (round time − the slowest host's wall time) / participants."""
    copies_per_host: int
    refs: dict[str, float] = field(default_factory=dict)
    ref_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    key: str = ""
    """The case's name in :data:`CASES`."""
    window: str = ""
    """The rounds pooled, first–last (1-based)."""


def round_walls(records: list[dict]) -> None:
    """Each record's ``round_wall_s``: wall time since the round before's θ̃ (``wall_time_s``
    apart, less this round's evaluation), so that what the server does between rounds counts;
    ``round_time_s`` for the first. Until the server wrote a round's record while the next one
    trained, that writing (~15–40 ms a round at K = 1,000) fell between the rounds, where
    ``round_time_s`` alone did not see it."""
    previous = None
    for record in records:
        if previous is None:
            record["round_wall_s"] = record["round_time_s"]
        else:
            evaluation = record.get("eval_time_s") or 0.0
            record["round_wall_s"] = record["wall_time_s"] - previous["wall_time_s"] - evaluation
        previous = record


def _sampled_copies(case: Case) -> list[int]:
    """B_k of the agents one host trains in a round (for reference (b): the same MLPs)."""
    run = compose(case.overrides())
    rng = np.random.default_rng(0)
    per_host = min(case.per_host, case.agents)
    count = per_host if case.per_round is None else max(case.per_round * per_host // case.agents, 1)
    chosen = rng.choice(per_host, size=count, replace=False)
    return [agent_profile(run, int(k)).budget.batch_size for k in chosen]  # type: ignore[attr-defined]


def whole_round_rate(rounds: list[dict]) -> float:
    """Env steps per second of wall time from one θ̃ to the next over ``rounds`` (records
    with :func:`round_walls`' ``round_wall_s``), all hosts together."""
    steps = sum(a["env_steps"] for r in rounds for a in r["agents"])
    return steps / sum(r["round_wall_s"] for r in rounds)


def _summary(case: Case, name: str, rounds: list[dict], refs: dict[str, list[float]],
             copies: int, first_round_s: float, peak: int) -> CaseResult:  # fmt: skip
    steps = [sum(a["env_steps"] for a in r["agents"]) for r in rounds]
    sample_s = [sum(a.get("engine_sample_s", float("nan")) for a in r["agents"]) for r in rounds]
    overhead = [
        (r["round_time_s"] - max(a["local_wall_s"] for a in r["agents"])) / len(r["agents"])
        for r in rounds
    ]
    return CaseResult(
        case=replace(case, name=name),
        start_to_round_1_s=first_round_s,
        peak_pss_mib=peak / 2**20,
        participants=statistics.median(len(r["agents"]) for r in rounds),
        env_steps_per_round=statistics.mean(steps),
        sampling_steps_per_cpu_s=sum(steps) / sum(sample_s),
        round_steps_per_s=whole_round_rate(rounds),
        round_time_s=statistics.median(r["round_wall_s"] for r in rounds),
        coordination_us_per_agent=1e6 * statistics.median(overhead),
        copies_per_host=copies,
        refs={name: statistics.median(values) for name, values in refs.items()},
        ref_ranges={name: (min(values), max(values)) for name, values in refs.items()},
    )


REF_REPEATS = 3
"""Measurements of each reference before the federation, and as many after it."""
FINAL_THETA: dict[str, torch.Tensor] = {}
"""θ̃ at the end of each case (for the in-process cross-check at a trained θ̃)."""


def _references(case: Case, copies: list[int], refs: dict[str, list[float]]) -> None:
    for _ in range(REF_REPEATS):
        refs["a_bare_gym"].append(bare_loop(sum(copies), 300))
        refs["b_gym_plus_forward"].append(forward_loop(copies, (case.hidden, case.hidden), 300))


def measure(
    case: Case,
    key: str,
    tree: engine_ab.Tree = engine_ab.THIS_TREE,
    refs: dict[str, list[float]] | None = None,
) -> list[CaseResult]:
    """The case's figures over all its rounds, or, for a case that trains long enough for
    the episodes to lengthen, over its first and its last three rounds separately, with
    ``tree``'s ``fedhpg-run`` (this environment's, or a commit's). The references measured
    around it are added to ``refs`` (where given, another tree's too: :func:`with_refs`)."""
    copies = _sampled_copies(case)
    if refs is None:
        refs = {"a_bare_gym": [], "b_gym_plus_forward": []}
    _references(case, copies, refs)
    runs: list[list[dict]] = []
    starts: list[float] = []
    peak = 0
    for _ in range(case.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            env = dict(tree.env)
            if case.cold_cache:
                env["NUMBA_CACHE_DIR"] = str(Path(tmp) / "numba")
            records, first_round_s, run_peak = _federation(
                case.overrides(), Path(tmp), sample_memory=True, poll_s=0.05, env=env,
                command=tree.command,
            )  # fmt: skip
            checkpoint = latest_valid_checkpoint(Path(tmp) / "checkpoints")
            if checkpoint is not None and tree.command is None:  # the runs are seeded alike
                FINAL_THETA[case.name] = checkpoint.theta
        round_walls(records)
        # Round 1 is start-up (first messages, first-touch of the buffers; the start-up column
        # times it): the throughput columns are of the rounds after it.
        runs.append([r for r in records if r["agents"]])
        starts.append(first_round_s)
        peak = max(peak, run_peak)
    _references(case, copies, refs)
    first_round_s = statistics.median(starts)
    length = len(runs[0])
    name = case.name if case.repeats == 1 else f"{case.name} ({case.repeats} runs)"

    def window(label: str, first: int, last: int) -> CaseResult:
        """Rounds ``first``..``last`` (1-based) of every run, pooled."""
        pooled = [r for rounds in runs for r in rounds[first - 1 : last]]
        result = _summary(case, label, pooled, refs, sum(copies), first_round_s, peak)
        return replace(result, key=key, window=f"{first}–{last}")

    if length < 10:
        return [window(name, min(2, length), length)]
    return [
        window(f"{name}, rounds 2–4", 2, 4),
        window(f"{name}, rounds {length - 2}–{length}", length - 2, length),
        window(f"{name}, rounds 2–{length}", 2, length),
    ]


CASES = {
    # 30 rounds: the policy learns, episodes grow from ~20 steps to the 500-step limit
    "k1000": Case("K = 1,000, all train", agents=1000, per_host=500, rounds=30, repeats=2),
    # the same federation with the environments in torch (envs/device/cartpole.py) and the
    # torch engine on this CPU: the device-resident path where no GPU is at hand
    "device": Case(
        "K = 1,000, all train, torch CartPole on the CPU",
        agents=1000,
        per_host=500,
        rounds=30,
        extra=("algo.engine=torch",),
    ),
    "k10000": Case(
        "K = 10,000, 1,000 per round", agents=10_000, per_host=5000, per_round=1000, repeats=3
    ),
    "processes": Case("one process per agent, K = 100", agents=100, per_host=1, rounds=3),
    "cold": Case(
        "K = 1,000, all train, numba cache empty",
        agents=1000,
        per_host=500,
        rounds=3,
        cold_cache=True,
    ),
    "overhead": Case(
        "K = 1,000, d ≈ 10⁴ (96-96 MLP)", agents=1000, per_host=500, hidden=96, rounds=4
    ),
}


def _b(r: CaseResult) -> float:
    return r.refs["b_gym_plus_forward"]


def per_core(r: CaseResult) -> float:
    """Whole-round env steps per second per core the hosts use, as a multiple of (b)."""
    return r.round_steps_per_s / min(-(-r.case.agents // r.case.per_host), CORES) / _b(r)


def sampling(r: CaseResult) -> float:
    """Env steps per CPU second of sampling, as a multiple of (b)."""
    return r.sampling_steps_per_cpu_s / _b(r)


def table(results: list[CaseResult]) -> str:
    lines = [
        "| case | start → end of round 1 (s) | peak PSS (MiB) | agents per round | env steps "
        "per round | sampling: steps per CPU-s | vs (b) | round: steps/s (all hosts) | per "
        "core vs (b) | (a) bare gym (M/s) | (b) + forward (M/s, median; range) | coordination "
        "per agent (µs) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        b = _b(r)
        low, high = r.ref_ranges.get("b_gym_plus_forward", (b, b))
        lines.append(
            f"| {r.case.name} | {r.start_to_round_1_s:.1f} | {r.peak_pss_mib:,.0f} | "
            f"{r.participants:,.0f} | {r.env_steps_per_round:,.0f} | "
            f"{r.sampling_steps_per_cpu_s / 1e6:.2f} M | {sampling(r):.2f} | "
            f"{r.round_steps_per_s / 1e6:.2f} M | {per_core(r):.2f} | "
            f"{r.refs['a_bare_gym'] / 1e6:.1f} | {b / 1e6:.2f} "
            f"({low / 1e6:.2f}–{high / 1e6:.2f}) | "
            f"{r.coordination_us_per_agent:.0f} |"
        )
    return "\n".join(lines)


def with_refs(results: list[CaseResult], refs: dict[str, list[float]]) -> list[CaseResult]:
    """``results`` against the median of ``refs`` (both trees' measurements of a case pooled:
    one yardstick, so that the trees' ratios to it compare as their throughputs do)."""
    medians = {name: statistics.median(values) for name, values in refs.items()}
    ranges = {name: (min(values), max(values)) for name, values in refs.items()}
    return [replace(r, refs=medians, ref_ranges=ranges) for r in results]


class _Picked:
    """One tree's results by case: a case's windows are early, late and all rounds, in that
    order (a short case has one window, which is all three)."""

    def __init__(self, results: list[CaseResult]) -> None:
        self.windows: dict[str, list[CaseResult]] = {}
        for r in results:
            self.windows.setdefault(r.key, []).append(r)

    def get(self, key: str, which: str = "all") -> CaseResult | None:
        found = self.windows.get(key)
        if not found:
            return None
        return found[{"early": 0, "late": 1 if len(found) > 1 else 0, "all": -1}[which]]

    def cell(self, *parts: tuple[str, str, Callable[[CaseResult], float], str]) -> str:
        """The values of (case, window, figure, format) joined by " / ", "—" for a case this
        tree did not run."""
        values = []
        for key, which, value, form in parts:
            r = self.get(key, which)
            values.append("—" if r is None else format(value(r), form))
        return " / ".join(values)


def _window(picked: _Picked, key: str, which: str) -> str:
    r = picked.get(key, which)
    return "" if r is None else r.window


TARGETS: list[tuple[str, str, str, Callable[[CaseResult], float], float, bool]] = [
    ("the whole round per core at K = 1,000 (early rounds)", "k1000", "early", per_core, 0.3,
     True),
    ("the whole round per core at K = 10,000", "k10000", "all", per_core, 0.3, True),
    ("sampling at K = 1,000", "k1000", "all", sampling, 0.7, True),
    ("sampling at K = 10,000", "k10000", "all", sampling, 0.7, True),
    ("start-up at K = 10,000", "k10000", "all", lambda r: r.start_to_round_1_s, 10.0, False),
    ("peak PSS at K = 10,000", "k10000", "all", lambda r: r.peak_pss_mib, 2048.0, False),
    ("coordination at d ≈ 10⁴", "overhead", "all", lambda r: r.coordination_us_per_agent, 50.0,
     False),
]  # fmt: skip
"""(what, case, window, figure, target, whether the target is a floor)."""


def _met(picked: _Picked) -> tuple[list[str], list[str]]:
    met: list[str] = []
    missed: list[str] = []
    for what, key, which, value, target, floor in TARGETS:
        r = picked.get(key, which)
        if r is not None:
            ok = value(r) >= target if floor else value(r) <= target
            (met if ok else missed).append(what)
    return met, missed


def _listed(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def summary_table(
    this: list[CaseResult], that: list[CaseResult], against: str | None
) -> results_file.Table:
    """The cases at their targets, this tree beside ``against`` (``that``: its results, run
    on the same machine the same hour; none: not run)."""
    sides = [_Picked(this), _Picked(that)]
    mine = sides[0]
    early, late, whole = (_window(mine, "k1000", w) for w in ("early", "late", "all"))
    device = _window(mine, "device", "all")
    rows = [
        (f"K = 1,000, whole round per core vs (b), rounds {early}",
         [("k1000", "early", per_core, ".2f")], "0.3"),
        (f"K = 1,000, rounds {late} / {whole}",
         [("k1000", "late", per_core, ".2f"), ("k1000", "all", per_core, ".2f")], ""),
        ("K = 10,000 (1,000 a round), whole round per core",
         [("k10000", "all", per_core, ".2f")], "0.3"),
        (f"sampling vs (b), K = 1,000 (rounds {whole}) / 10,000",
         [("k1000", "all", sampling, ".2f"), ("k10000", "all", sampling, ".2f")], "0.7"),
        ("start-up, K = 1,000 / 10,000 (s)",
         [(k, "all", lambda r: r.start_to_round_1_s, ".1f") for k in ("k1000", "k10000")], "10"),
        ("start-up with numba's cache empty, K = 1,000 (s)",
         [("cold", "all", lambda r: r.start_to_round_1_s, ".1f")], ""),
        ("peak PSS, K = 1,000 / 10,000 (MiB)",
         [(k, "all", lambda r: r.peak_pss_mib, ",.0f") for k in ("k1000", "k10000")], "2,048"),
        ("one process per agent, K = 100: whole round per core vs (b) / peak PSS (MiB)",
         [("processes", "all", per_core, ".2f"),
          ("processes", "all", lambda r: r.peak_pss_mib, ",.0f")], ""),
        ("d ≈ 10⁴: whole round per core vs (b) / coordination (µs an agent)",
         [("overhead", "all", per_core, ".2f"),
          ("overhead", "all", lambda r: r.coordination_us_per_agent, ".0f")], "— / 50"),
        (f"K = 1,000 on the torch CartPole (the device-resident path, on the CPU), rounds "
         f"{device}: whole round per core / sampling vs (b)",
         [("device", "all", per_core, ".2f"), ("device", "all", sampling, ".2f")], ""),
        ("(b), K = 1,000 / 10,000 (M steps/s, median)",
         [(k, "all", lambda r: _b(r) / 1e6, ".2f") for k in ("k1000", "k10000")], ""),
    ]  # fmt: skip
    built = [[label, *(side.cell(*parts) for side in sides), target]
             for label, parts, target in rows]  # fmt: skip
    met, missed = _met(mine)
    sentences = []
    if met:
        sentences.append(f"At this tree {_listed(met)} meet their targets")
    if missed:
        sentences.append(f"{_listed(missed)} do not")
    summary = "; ".join(sentences) + "."
    if that and against:
        theirs_met, _ = _met(sides[1])
        summary += (
            f" At {against}, on the same machine: {_listed(theirs_met)} meet theirs."
            if theirs_met
            else f" At {against}, on the same machine, none of them does."
        )
    ratios = []
    for what, key, which in ((f"at K = 1,000 (rounds {early})", "k1000", "early"),
                             ("at K = 10,000", "k10000", "all"),
                             ("with one process per agent", "processes", "all")):  # fmt: skip
        mine_r, theirs_r = sides[0].get(key, which), sides[1].get(key, which)
        if mine_r is not None and theirs_r is not None:
            ratio = mine_r.round_steps_per_s / theirs_r.round_steps_per_s
            ratios.append(f"{ratio:.2f} {what}")
    if ratios and against:
        summary += f" Whole-round env steps per second, this tree ÷ {against}: {_listed(ratios)}."
    column = f"{against}, same machine" if against else "no commit run"
    summary = summary[0].upper() + summary[1:]
    figure = results_file.Figure(path=_relative(FIGURE), caption="the cases against their targets")
    return {"columns": ["case", "this tree", column, "target"], "rows": built,
            "summary": summary, "figure": figure}  # fmt: skip


DEVICE_ROW = ("k1000", "device")
"""The cases of the device-resident path's comparison with the compiled engine."""
DEVICE_ROW_RESULTS = RESULTS.with_name("scale_device_row.json")


def device_row_table(results: list[CaseResult]) -> str:
    """The compiled engine's and the torch path's K = 1,000 federations, side by side."""
    lines = [
        "| case | env steps per round | sampling: steps per CPU-s | vs (b) | round: steps/s "
        "| per core vs (b) |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {_device_case(r)} | {r.env_steps_per_round:,.0f} | "
            f"{r.sampling_steps_per_cpu_s / 1e6:.2f} M | {sampling(r):.2f} | "
            f"{r.round_steps_per_s / 1e6:.2f} M | {per_core(r):.2f} |"
        )
    return "\n".join(lines)


def device_row_summary(results: list[CaseResult]) -> str:
    compiled = next(r for r in results if "algo.engine=torch" not in r.case.extra)
    torch_path = next(r for r in results if "algo.engine=torch" in r.case.extra)
    sampling = compiled.sampling_steps_per_cpu_s / torch_path.sampling_steps_per_cpu_s
    rounds = compiled.round_steps_per_s / torch_path.round_steps_per_s
    return (
        f"On the CPU the device-resident path samples {sampling:.0f}× slower than the compiled "
        f"engine and runs whole rounds {rounds:.0f}× slower: it is for a GPU, and on a CPU the "
        "compiled engine stays the default (`algo.engine=auto`)."
    )


def _relative(path: Path) -> str:
    """``path`` from the repository's root where it lies inside it."""
    root = RESULTS.parents[2].resolve()
    full = path.resolve()
    return str(full.relative_to(root)) if full.is_relative_to(root) else str(path)


def _device_case(r: CaseResult) -> str:
    runs = f" ({r.case.repeats} runs)" if r.case.repeats > 1 else ""
    if "algo.engine=torch" in r.case.extra:
        return f"torch CartPole, torch engine, CPU{runs}"
    return f"compiled engine{runs}"


def _write_device_row(results: list[CaseResult], data: Path, machine: str) -> None:
    data.write_text(json.dumps({
        "machine": machine,
        "cases": _stored(results),
        "against_baseline": [],
    }, indent=1) + "\n")  # fmt: skip
    results_file.write(
        "scale_device_row",
        title="Thousands of agents: the device-resident path on the CPU",
        order=183,
        command=results_file.command_line("benchmarks.scale"),
        measures=[
            *results_file.RUNTIME_CODE,
            "common/learning/engine",
            "common/learning/batched",
            "envs/device",
        ],
        setup=(
            "The same federation (K = 1,000, 2 hosts of 500, population budgets) on the "
            "compiled engine and on the torch engine with the torch CartPole."
        ),
        data=[_relative(data)],
        tables=[
            results_file.table_from_markdown(device_row_table(results), device_row_summary(results))
        ],
    )


def figure(results: list[CaseResult], machine: str) -> None:
    """Left: the federation's throughput as a multiple of reference (b), sampling and whole
    round per core, against their targets 0.7 and 0.3; right: peak PSS against 2 GB. The
    one-process-per-agent case is left out of the ratios (its (b) is one agent's copies)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.8), width_ratios=[3, 2])
    names = [r.case.name for r in results]
    y = np.arange(len(results))
    hosted = [r.case.per_host > 1 for r in results]
    for offset, (label, values, target) in enumerate([
        ("sampling", [sampling(r) for r in results], 0.7),
        ("whole round, per core", [per_core(r) for r in results], 0.3),
    ]):  # fmt: skip
        bars = left.barh(y[hosted] + 0.2 - 0.4 * offset, np.asarray(values)[hosted], height=0.4,
                         label=f"{label} (target {target})")  # fmt: skip
        left.axvline(target, color=bars.patches[0].get_facecolor(), linestyle="--", lw=1)
    left.set_yticks(y, names, fontsize=8)
    left.set_xlabel("env steps per second ÷ reference (b)")
    left.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    right.barh(y, [r.peak_pss_mib for r in results])
    right.axvline(2048, color="k", linestyle="--", label="2 GB target")
    right.set_yticks(y, [""] * len(y))
    right.set_xlabel("peak PSS of the federation (MiB)")
    right.legend(fontsize=7, loc="lower right")
    fig.suptitle(
        f"fedhpg at scale (make bench-scale; (b) = gym + every agent's forward)\n{machine}",
        fontsize=10,
    )
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=120)


def _results(entries: list[dict]) -> list[CaseResult]:
    out = []
    for entry in entries:
        case = Case(**{**entry["case"], "extra": tuple(entry["case"]["extra"])})
        fields = {k: v for k, v in entry.items() if k != "case"}
        fields["ref_ranges"] = {k: tuple(v) for k, v in fields["ref_ranges"].items()}
        out.append(CaseResult(case=case, **fields))
    return out


def _stored(results: list[CaseResult]) -> list[dict]:
    return [{**asdict(r), "case": asdict(r.case)} for r in results]


def _load(path: Path = RESULTS) -> tuple[list[CaseResult], str]:
    stored = json.loads(path.read_text())
    return _results(stored["cases"]), stored.get("machine", "CPU not recorded")


def stored_table(path: Path = RESULTS) -> results_file.Table:
    """The summary table from the stored runs of both trees."""
    stored = json.loads(path.read_text())
    return summary_table(
        _results(stored["cases"]), _results(stored.get("baseline_cases", [])), stored.get("against")
    )


SETUP = (
    "Real `fedhpg-run` federations on loopback: CartPole variants, 16-16 MLP, B_k and τ_k from "
    '`agents=population`, counted clock, two agent hosts. "Sampling" is env steps per '
    'CPU-second of the hosts\' sampling; "whole round per core" is env steps per second of wall '
    "time from one θ̃ to the next, divided by the hosts' cores (at most the machine's), against "
    "reference (b): `gym.make_vec` CartPole with every agent's own MLP forward and draw per "
    "step, in the benchmark's process. The commit's column is every case run again with that "
    "commit's own `fedhpg-run` right after this tree's, the same harness reading its metrics, "
    "and both trees' runs of a case are against one (b): the median of the references measured "
    "around both. "
    "Ratios to (b) do not carry from one machine to another. `make bench-scale` runs it."
)


def against_baseline() -> list[engine_ab.Comparison]:
    """This tree's agent groups against :data:`benchmarks.engine_ab.BASELINE`'s, one host's
    500 agents of the K = 1,000 case at θ̃_0 and at its final θ̃, and FedHPGVR at K = 1,000
    (:mod:`benchmarks.engine_ab`: interleaved rounds, paired ratios)."""
    setups = [engine_ab.Setup(rounds=8)]
    with tempfile.TemporaryDirectory() as tmp:
        trained = FINAL_THETA.get(CASES["k1000"].name)
        if trained is not None:
            path = Path(tmp) / "trained.pt"
            torch.save(trained, path)
            label = f"θ̃ after {CASES['k1000'].rounds} rounds"
            setups.append(engine_ab.Setup(rounds=4, theta=str(path), label=label))
        setups.append(engine_ab.Setup(algo="fedhpgvr", agents=1000, rounds=2))
        return [engine_ab.compare(setup) for setup in setups]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="*", choices=[[], *CASES], help="default: all")
    parser.add_argument("--plot-only", action="store_true", help="redraw from scale.json")
    parser.add_argument("--out", type=Path, help="write a subset's results here (JSON)")
    parser.add_argument(
        "--against",
        default=engine_ab.BASELINE,
        help="the commit every case runs at too (default %(default)s)",
    )
    parser.add_argument(
        "--skip-baseline",
        action="store_true",
        help="run no case at the commit and no engine comparison with it",
    )
    parser.add_argument("--tables-only", action="store_true",
                        help="the summary table again from scale.json")  # fmt: skip
    parser.add_argument("--rounds", type=int, help="a subset's cases run this many rounds")
    args = parser.parse_args()
    if args.rounds is not None and (not args.cases or args.rounds < 2):
        parser.error("--rounds: a subset of cases only, and at least 2 rounds")
    if args.tables_only:
        rebuilt = stored_table()
        results_file.rerender("scale", [rebuilt])
        print(rebuilt["summary"])
        return
    if args.plot_only:
        stored, machine = _load()
        print(f"machine: {machine}")
        print(table(stored))
        figure(stored, machine)
        return
    args.cases = args.cases or list(CASES)
    machine = cpu_description()
    print(f"machine: {machine}", flush=True)
    # the device row compares two engines of this tree; every other run compares the commit
    alone = args.skip_baseline or sorted(args.cases) == sorted(DEVICE_ROW)
    that = None if alone else engine_ab.baseline_tree(args.against)
    results: list[CaseResult] = []
    theirs: list[CaseResult] = []
    for name in args.cases:
        case = CASES[name]
        if args.rounds is not None:
            case = replace(case, name=f"{case.name} ({args.rounds} rounds)", rounds=args.rounds)
        refs: dict[str, list[float]] = {"a_bare_gym": [], "b_gym_plus_forward": []}
        measured = measure(case, name, refs=refs)
        at_commit: list[CaseResult] = []
        if that is not None:  # the same case at the commit, right after
            try:
                at_commit = measure(case, name, that, refs)
            except RuntimeError as error:  # a case the commit cannot run: "—" in its column
                print(f"{name} at {that.label}: {str(error).splitlines()[-1]}", flush=True)
        results += with_refs(measured, refs)
        theirs += with_refs(at_commit, refs)
        print("\n".join(table(with_refs(measured, refs)).splitlines()[2:]), flush=True)
        if at_commit:
            print(f"at {that.label}:" if that else "", flush=True)
            print("\n".join(table(with_refs(at_commit, refs)).splitlines()[2:]), flush=True)
    print(table(results))
    engine = [] if args.skip_baseline else against_baseline()
    print("\n".join(engine_ab.report(c) for c in engine))
    against = None if that is None else args.against
    print(summary_table(results, theirs, against)["summary"])
    data = json.dumps({
        "machine": machine, "cases": _stored(results), "against": against,
        "baseline_cases": _stored(theirs), "against_baseline": [asdict(c) for c in engine],
    }, indent=1) + "\n"  # fmt: skip
    if sorted(args.cases) == sorted(DEVICE_ROW):
        _write_device_row(results, args.out or DEVICE_ROW_RESULTS, machine)
        return
    if len(args.cases) < len(CASES):
        # a subset is a spot check: the results file and the figure hold the whole table
        if args.out is not None:
            args.out.write_text(data)
        return
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(data)
    figure(results, machine)
    path = results_file.write(
        "scale",
        title="Thousands of agents on agent hosts",
        order=160,
        command=results_file.command_line("benchmarks.scale"),
        measures=MEASURES,
        setup=SETUP,
        data=[_relative(RESULTS)],
        tables=[stored_table()],
        keep_summaries=False,
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
