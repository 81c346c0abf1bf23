"""``make bench-device``: the whole local iteration of K agents on one device, against a
reference measured in the same run.

CartPole variants (``env=cartpole``, level 0.5: every agent its own physics), each agent's
16-16 MLP, B = 16 trajectories, one local iteration per round (sampling, the estimator, the
gradient and the step, on the engine: ``algo.engine=torch algo.device=DEVICE``, the torch
CartPole stepping on the device), K ∈ ``--agents``. For each K:

- env steps per second of the whole local iteration (a round of one iteration: θ̃ to the
  device, the iteration, the θ rows and statistics back), the median of ``--repeats`` rounds
  after one unmeasured; at θ̃₀ (episodes of ~20 steps, a few of hundreds) and at a policy that
  balances every pole for the 500 steps (every copy alive to the horizon: the reference's
  regime);
- the device's peak memory (CUDA: torch's peak allocation; the CPU: the growth of the
  process's peak resident memory) beside the memory plan's;
- the reference (:mod:`benchmarks.device_reference`: K × 16 copies, 64 steps with auto-reset,
  sampling alone and with its REINFORCE gradient and step), measured in the same process, and
  up to ``--compare-up-to`` agents the same round on the compiled engine on this machine's CPU.

The placement check: whether an agent's θ after 3 rounds is bit-identical alone, in four
companies and on a second run, on the device, for every torch family (CartPole; GridWorld and
its own draws; Pendulum, a Gaussian policy; Acrobot; MountainCar).

Each part can run alone (``--only``), writing its JSON as it goes, so that
``benchmarks/on_device.sh`` runs each under its own time limit and a stopped part keeps what
it measured; ``--report`` gathers the parts (and a federation's run directory) in one JSON and
one table.

    bash benchmarks/on_device.sh local                          # make bench-device
    python -m benchmarks.scale_device --device cpu --agents 100 --repeats 2   # all parts here
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import statistics
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from benchmarks.device_reference import measure as reference
from benchmarks.scale_refs import cpu_description
from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.algo import DEVICE_PATTERN
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.batched.backend import CompiledBackend
from fedhpg.common.learning.engine.devices import device_problem
from fedhpg.common.learning.group import EngineGroup, make_agent_group
from fedhpg.common.learning.policies import get_flat_params
from fedhpg.common.learning.worker import build_policy, initial_theta
from fedhpg.common.runtime.cli import compose
from fedhpg.common.runtime.memory import tune_malloc_for_engine

logger = logging.getLogger("benchmarks.scale_device")

RESULTS = Path(__file__).parent / "results" / "scale_device.json"
BATCH = 16
OVERRIDES = [
    "env=cartpole", f"agents.budget.batch_size=[{BATCH}]", "agents.budget.local_iters=[1]",
    "agents.speeds=[1]", "agents.step_delays_s=[0]", "agents.clock=counted",
    "policy.hidden=[16,16]",
]  # fmt: skip
BALANCING_GAINS = (0.1, 0.5, 10.0, 2.0)
"""Push right when 0.1 x + 0.5 ẋ + 10 θ + 2 θ̇ > 0: every variant's pole stays up 500 steps."""
WARM_UP_AGENTS = 20
MIB = 2**20


@dataclass(frozen=True)
class Row:
    agents: int
    policy: str
    """'initial' (θ̃₀) or 'balancing' (every episode to the horizon)."""
    env_steps: int
    """Of one local iteration of the K agents."""
    iteration_s: float
    steps_per_s: float
    device_peak_mib: float | None
    """CUDA: the peak allocation during the measured rounds; the CPU: how far the process's
    peak resident memory lies above its resident memory before them. The process's malloc is
    tuned as an engine's agent process tunes it (blocks of 16 MiB and more returned on free,
    up to 64 MiB of freed heap kept), so this overstates what lives by at most that."""
    planned_peak_mib: float
    chunks: int
    compiled_steps_per_s: float | None
    """The same round on the compiled engine on this machine's CPU (None: not compared)."""
    measured_rounds: int = 0
    """Rounds timed after the unmeasured one (0: only that one fitted in the time limit, and
    its time is the row's)."""


@dataclass(frozen=True)
class ReferenceRow:
    agents: int
    sampling_steps_per_s: float
    with_gradient_steps_per_s: float
    peak_mib: float | None


def _run(agents: int, device: str, engine: str = "torch") -> RunConfig:
    return compose([*OVERRIDES, f"agents.num_agents={agents}", f"algo.engine={engine}",
                    f"algo.device={device}"])  # fmt: skip


def balancing_theta(run: RunConfig) -> torch.Tensor:
    """A 16-16 MLP whose logits are ±(gains · s), near-deterministic (:data:`BALANCING_GAINS`)."""
    policy = build_policy(variants_of(run, [0])[0], run)
    net = policy.net  # type: ignore[attr-defined]
    with torch.no_grad():
        for parameter in policy.parameters():
            parameter.zero_()
        net[0].weight[0] = 0.01 * torch.tensor(BALANCING_GAINS)  # tanh stays linear
        net[2].weight[0, 0] = 1.0
        net[4].weight[0, 0], net[4].weight[1, 0] = -5000.0, 5000.0
    return get_flat_params(policy)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def _rss() -> int:
    """This process's resident memory now."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * resource.getpagesize()


class _PeakRss:
    """The largest resident size of this process while the block runs, read every 2 ms (the
    kernel's ru_maxrss is the process's lifetime high-water mark, which earlier work in the
    same process, a smaller K's or another test's, may already have set higher)."""

    def __enter__(self) -> _PeakRss:
        self.peak = _rss()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self) -> None:
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, _rss())

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss())


@dataclass(frozen=True)
class Measured:
    steps: int
    """Env steps of one iteration."""
    seconds: float
    """The median of the measured rounds (the unmeasured one's where none fitted)."""
    peak_mib: float | None
    rounds: int
    """Rounds measured after the unmeasured one (0: only that one fitted before the deadline)."""


def iterations(group: EngineGroup, theta: torch.Tensor, agents: list[int], device: str,
               repeats: int, deadline: float | None = None) -> Measured:  # fmt: skip
    """Env steps of one iteration, the median seconds and the peak over up to ``repeats``
    rounds after an unmeasured one: as many as fit before ``deadline``, judged by the
    unmeasured round."""
    cuda = device.startswith("cuda")
    before = _rss()  # the unmeasured round's peak counts too: it is the same round
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)
    with _PeakRss() as resident:
        times, steps, repeats = _rounds(group, theta, agents, device, repeats, deadline)
    peak = torch.cuda.max_memory_allocated(device) if cuda else resident.peak - before
    middle = sorted(range(len(times)), key=times.__getitem__)[len(times) // 2]
    return Measured(steps[middle], times[middle], peak / MIB, max(repeats, 0))


def timed_round(
    group: EngineGroup, theta: torch.Tensor, agents: list[int], device: str, index: int
) -> tuple[float, int]:
    """Round ``index`` of ``agents`` from ``theta``, between device synchronisations: its
    seconds and env steps."""
    _sync(device)
    started = time.perf_counter()
    trained = group.train(index, theta, agents)
    _sync(device)
    return time.perf_counter() - started, sum(trained.result.stats.env_steps)


def _rounds(
    group: EngineGroup,
    theta: torch.Tensor,
    agents: list[int],
    device: str,
    repeats: int,
    deadline: float | None,
) -> tuple[list[float], list[int], int]:
    """:func:`iterations`' rounds: their seconds, env steps, and how many were measured."""
    first, first_steps = timed_round(group, theta, agents, device, 1)
    times, steps = [first], [first_steps]
    if deadline is not None:
        repeats = min(repeats, int((deadline - time.perf_counter()) / (1.2 * first)))
    if repeats > 0:
        times, steps = [], []
    for repeat in range(repeats):
        seconds, taken = timed_round(group, theta, agents, device, 2 + repeat)
        times.append(seconds)
        steps.append(taken)
    return times, steps, repeats


def measure_engine(agents: int, device: str, repeats: int, compare: bool,
                   max_iteration_s: float, deadline: float | None = None,
                   done: Callable[[Row], None] = lambda row: None) -> list[Row]:  # fmt: skip
    """The rows of K = ``agents``, θ̃₀ first; ``deadline`` (a ``time.perf_counter()``) cuts
    the repeats to what fits and skips what cannot start before it."""
    run = _run(agents, device)
    indices = list(range(agents))
    group = make_agent_group(run, indices, variants_of(run, indices))
    assert isinstance(group, EngineGroup)
    assert not isinstance(group.engine.backend, CompiledBackend)
    group.prepare()
    plan = group.plan(indices)
    logger.info("K = %d: planned peak %.0f MiB in %d chunk(s) of <= %d agents", agents,
                plan.peak_bytes / MIB, len(plan.chunks), plan.per_chunk)  # fmt: skip
    compiled_group = None
    if compare:
        cpu = _run(agents, "cpu", engine="auto")
        compiled_group = make_agent_group(cpu, indices, variants_of(cpu, indices))
        assert isinstance(compiled_group, EngineGroup)
        assert isinstance(compiled_group.engine.backend, CompiledBackend)
        compiled_group.prepare()
    rows = []
    for name, theta in (("initial", initial_theta(variants_of(run, [0])[0], run)),
                        ("balancing", balancing_theta(run))):  # fmt: skip
        measured = iterations(group, theta, indices, device, repeats, deadline)
        compiled = None
        if compiled_group is not None:
            c = iterations(compiled_group, theta, indices, "cpu", repeats, deadline)
            compiled = c.steps / c.seconds
        row = Row(
            agents=agents, policy=name, env_steps=measured.steps,
            iteration_s=measured.seconds, steps_per_s=measured.steps / measured.seconds,
            device_peak_mib=measured.peak_mib, planned_peak_mib=plan.peak_bytes / MIB,
            chunks=len(plan.chunks), compiled_steps_per_s=compiled,
            measured_rounds=measured.rounds,
        )  # fmt: skip
        rows.append(row)
        done(row)
        logger.info("K = %d, %s: %.3g s an iteration (%d measured), %.3g steps/s, peak %.0f MiB",
                    agents, name, measured.seconds, measured.rounds,
                    row.steps_per_s, measured.peak_mib or 0.0)  # fmt: skip
        if measured.seconds > max_iteration_s:
            logger.warning(
                "K = %d: an iteration took %.0f s > --max-iteration-s: the "
                "balancing policy is not measured",
                agents,
                measured.seconds,
            )
            break
    group.close()
    return rows


def measure_reference(agents: int, device: str, repeats: int) -> ReferenceRow:
    target = torch.device(device)
    sampling = reference(agents, BATCH, target, gradient=False, repeats=repeats)
    with_gradient = reference(agents, BATCH, target, gradient=True, repeats=repeats)
    peak = with_gradient.peak_bytes
    return ReferenceRow(
        agents=agents,
        sampling_steps_per_s=sampling.steps_per_s,
        with_gradient_steps_per_s=with_gradient.steps_per_s,
        peak_mib=None if peak is None else peak / MIB,
    )


PLACEMENT_FAMILIES = {
    "cartpole": ["env=cartpole", "policy.hidden=[16,16]"],
    "gridworld": ["env=gridworld"],
    "pendulum": ["env=pendulum", "policy.hidden=[16,16]", "env.horizon=100"],
    "acrobot": ["env=acrobot", "policy.hidden=[16,16]", "env.horizon=100"],
    "mountaincar": ["env=mountaincar", "policy.hidden=[16,16]", "env.horizon=100"],
}
PLACEMENT_KEYS = ("same_theta_in_any_company", "same_theta_on_a_second_run")


def placement_check(device: str, family: str) -> dict[str, bool]:
    """Whether, on ``device``, an agent's θ after round 3 is bit-identical in any company
    (alone, in small groups, all nine together) and on a second run, for ``family``
    (:data:`PLACEMENT_FAMILIES`; population budgets: rows of different batch sizes)."""
    run = compose([*PLACEMENT_FAMILIES[family], "agents=population", "agents.num_agents=9",
                   "algo.engine=torch", f"algo.device={device}"])  # fmt: skip
    theta = initial_theta(variants_of(run, [0])[0], run)

    def train(company: list[int]) -> dict[int, torch.Tensor]:
        group = make_agent_group(run, company, variants_of(run, company))
        assert isinstance(group, EngineGroup)
        result = group.train(3, theta, company).result
        return {k: torch.from_numpy(result.theta_of(k)) for k in company}

    everyone = train(list(range(9)))
    companies = [train(c) for c in ([4], [8, 0], [7, 2, 5], [6, 1, 3, 0, 8, 2, 4])]
    return {
        "same_theta_in_any_company": all(
            torch.equal(got[k], everyone[k]) for got in companies for k in got
        ),
        "same_theta_on_a_second_run": all(
            torch.equal(got, everyone[k]) for k, got in train(list(range(9))).items()
        ),
    }


def _cell(value: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "—" if value is None else f"{value / scale:,.{digits}f}"


def table(rows: list[Row], refs: dict[int, ReferenceRow]) -> str:
    lines = [
        "| K | policy | env steps / iteration | iteration (s) | engine (M steps/s) "
        "| reference sampling (M/s) | reference + gradient (M/s) | engine ÷ reference + "
        "gradient | device peak (MiB) | planned peak (MiB) | chunks | reference peak (MiB) "
        "| compiled CPU engine (M/s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ref = refs.get(r.agents)
        lines.append(
            f"| {r.agents:,} | {r.policy}{'' if r.measured_rounds else ' (1 round)'} "
            f"| {r.env_steps:,} | {r.iteration_s:.3f} | {r.steps_per_s / 1e6:.3g} "
            f"| {_cell(ref and ref.sampling_steps_per_s, 1e6, 1)} "
            f"| {_cell(ref and ref.with_gradient_steps_per_s, 1e6, 1)} "
            f"| {_cell(ref and r.steps_per_s / ref.with_gradient_steps_per_s)} "
            f"| {_cell(r.device_peak_mib, digits=0)} | {r.planned_peak_mib:,.0f} | {r.chunks} "
            f"| {_cell(ref and ref.peak_mib, digits=0)} | {_cell(r.compiled_steps_per_s, 1e6)} |"
        )
    return "\n".join(lines)


def _header(device: str) -> dict[str, object]:
    name = torch.cuda.get_device_name(device) if device.startswith("cuda") else "CPU"
    return {"device": device, "device_name": name, "machine": cpu_description(),
            "torch": torch.__version__, "batch": BATCH}  # fmt: skip


def _write(path: Path, record: dict[str, object]) -> None:
    """``record`` to ``path`` whole (a part killed at its limit leaves its last complete
    record)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial")
    partial.write_text(json.dumps(record, indent=1) + "\n")
    partial.replace(path)


def run_placement(device: str, families: list[str], out: Path) -> dict[str, object]:
    record: dict[str, object] = {"part": "placement", **_header(device), "families": {}}
    for family in families:
        started = time.perf_counter()
        held = placement_check(device, family)
        record["families"][family] = held  # type: ignore[index]
        _write(out, record)
        logger.info("placement, %s: %s (%.0f s)", family, held, time.perf_counter() - started)
    return record


def run_iteration(args: argparse.Namespace, counts: list[int]) -> dict[str, object]:
    deadline = None if args.time_limit_s is None else time.perf_counter() + args.time_limit_s
    record: dict[str, object] = {"part": "iteration", **_header(args.device),
                                 "rows": [], "reference": []}  # fmt: skip
    _run_warm_up(args.device, compiled=min(counts) <= args.compare_up_to)
    for agents in sorted(counts):
        ref = measure_reference(agents, args.device, args.repeats)
        record["reference"].append(asdict(ref))  # type: ignore[attr-defined]
        _write(args.out, record)
        logger.info("K = %d, reference: sampling %.3g steps/s, with its gradient %.3g, peak %s MiB",
                    agents, ref.sampling_steps_per_s, ref.with_gradient_steps_per_s,
                    _cell(ref.peak_mib, digits=0))  # fmt: skip
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()  # the engine plans on the device's free memory

        def done(row: Row) -> None:
            record["rows"].append(asdict(row))  # type: ignore[attr-defined]
            _write(args.out, record)

        measure_engine(agents, args.device, args.repeats, agents <= args.compare_up_to,
                       args.max_iteration_s, deadline, done)  # fmt: skip
    return record


def federation_record(run_dir: Path, agents: int, status: int, seconds: float) -> dict[str, object]:
    """What a ``fedhpg-run`` federation left in ``run_dir``: rounds done, their times, and the
    final evaluation's mean greedy return over the agents' environments."""
    rounds: list[dict[str, object]] = []
    metrics = run_dir / "metrics.jsonl"
    for line in metrics.read_text().splitlines() if metrics.exists() else []:
        entry = json.loads(line)
        row: dict[str, object] = {"round": entry["round"], "round_time_s": entry["round_time_s"],
                                  "updates": entry.get("updates")}  # fmt: skip
        evaluation = entry.get("eval")
        if evaluation:
            returns = [e["return_mean"] for e in evaluation.values()]
            row["eval_environments"] = len(returns)
            row["eval_mean_return"] = statistics.fmean(returns)
            row["eval_time_s"] = entry.get("eval_time_s")
        rounds.append(row)
    return {"part": "federation", "agents": agents, "exit_status": status,
            "seconds": seconds, "rounds": rounds}  # fmt: skip


def federation_line(federation: dict[str, Any]) -> str:
    done = federation["rounds"]
    line = (f"federation of {federation['agents']:,} agents on one host: {len(done)} of 3 "
            f"rounds done, exit status {federation['exit_status']} after "
            f"{federation['seconds']:.0f} s")  # fmt: skip
    if done:
        line += "; round times " + ", ".join(f"{r['round_time_s']:.1f} s" for r in done)
    evaluated = [r for r in done if "eval_mean_return" in r]
    if evaluated:
        line += (f"; θ̃ in {evaluated[-1]['eval_environments']:,} environments: mean greedy "
                 f"return {evaluated[-1]['eval_mean_return']:.1f}")  # fmt: skip
    return line


def report(parts: list[Path], out: Path, federation: dict[str, Any] | None) -> int:
    """The parts' records in one JSON and a table on stdout; 0 when every part finished and
    the placement check held."""
    record: dict[str, object] = {"parts": {}}
    rows: list[Row] = []
    refs: dict[int, ReferenceRow] = {}
    placement: dict[str, dict[str, bool]] = {}
    for path in parts:
        if not path.exists():
            continue
        part = json.loads(path.read_text())
        record["parts"][path.stem] = part  # type: ignore[index]
        for key in ("device", "device_name", "machine", "torch", "batch"):
            if key in part:
                record[key] = part[key]
        if part["part"] == "iteration":
            rows += [Row(**r) for r in part["rows"]]
            refs.update({r["agents"]: ReferenceRow(**r) for r in part["reference"]})
        elif part["part"] == "placement":
            placement.update(part["families"])
    if federation is not None:
        record["federation"] = federation
    print(f"device: {record.get('device_name', '?')}; host CPU: {record.get('machine', '?')}; "
          f"torch {record.get('torch', '?')}; CartPole, MLP 16-16, B = {BATCH}")  # fmt: skip
    print(table(rows, refs))
    missing = sorted(set(refs) - {r.agents for r in rows})
    if missing:
        print(f"no engine row (the part ran out of time) for K = {missing}")
    measured_k = sorted({r.agents for r in rows})
    if measured_k:
        largest = measured_k[-1]
        best = max(r.steps_per_s for r in rows if r.agents == largest)
        ref = refs.get(largest)
        ratio = None if ref is None else best / ref.with_gradient_steps_per_s
        record["largest_k"] = {"agents": largest, "engine_steps_per_s": best,
                               "over_reference_with_gradient": ratio}  # fmt: skip
        print(
            f"K = {largest:,}: engine {best / 1e6:.3g} M steps/s with gradients"
            + ("" if ratio is None else f", {ratio:.2f} × the reference with its gradient")
        )
    held = {key: all(f[key] for f in placement.values()) for key in PLACEMENT_KEYS}
    record["placement"] = {"families": placement, **held} if placement else None
    if placement:
        print(f"placement check (9 agents, round 3; {', '.join(placement)}): " + ", ".join(
            f"{key.replace('_', ' ')}: {'yes' if ok else 'NO'}" for key, ok in held.items()
        ))  # fmt: skip
    else:
        print("placement check: not finished")
    if federation is not None:
        print(federation_line(federation))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}")
    complete = bool(placement) and all(held.values()) and not missing and bool(rows)
    if federation is not None:
        complete &= federation["exit_status"] == 0 and len(federation["rounds"]) == 3
    return 0 if complete else 1


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--only", choices=["all", "placement", "iteration"], default="all",
                        help="one part of the benchmark (benchmarks/on_device.sh runs each "
                        "in its own process, under its own time limit)")  # fmt: skip
    parser.add_argument("--agents", default="1000,16000,65536",
                        help="comma-separated K to measure")  # fmt: skip
    parser.add_argument("--families", default=",".join(PLACEMENT_FAMILIES),
                        help="the placement check's families")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--compare-up-to", type=int, default=0,
                        help="also time the compiled engine on the CPU up to this K")  # fmt: skip
    parser.add_argument("--max-iteration-s", type=float, default=60.0,
                        help="skip the balancing policy after a slower first one")  # fmt: skip
    parser.add_argument("--time-limit-s", type=float, default=None,
                        help="fewer repeats where the rounds would not fit")  # fmt: skip
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--report",
        type=Path,
        nargs="*",
        default=None,
        metavar="PART",
        help="no measuring: the parts' JSON in one (--out) and a table",
    )
    parser.add_argument("--federation", nargs=4, metavar=("RUN_DIR", "AGENTS", "STATUS", "SECONDS"),
                        help="with --report: a fedhpg-run federation's run directory, its "
                        "number of agents, exit status and seconds")  # fmt: skip
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.report is not None:
        federation = None
        if args.federation is not None:
            run_dir, agents, status, seconds = args.federation
            federation = federation_record(Path(run_dir), int(agents), int(status), float(seconds))
        sys.exit(report(args.report, args.out, federation))
    try:
        counts = [int(k) for k in args.agents.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1 or args.repeats < 1:
        sys.exit("error: need --agents as positive integers (1000,16000) and --repeats >= 1")
    families = args.families.split(",")
    unknown = sorted(set(families) - set(PLACEMENT_FAMILIES))
    if unknown:
        sys.exit(f"error: --families: unknown {unknown}, allowed: {', '.join(PLACEMENT_FAMILIES)}")
    check_device_argument(args.device)
    torch.set_num_threads(1)
    # malloc as in an engine's agent process (common/runtime/memory.py), for the reference
    # too: at glibc's default 128 KiB threshold every step's [K·16, 16] activations would be
    # mmapped and faulted in again, which no agent process pays
    tune_malloc_for_engine()
    if args.only == "placement":
        run_placement(args.device, families, args.out)
        return
    if args.only == "iteration":
        run_iteration(args, counts)
        return
    placement_out = args.out.with_name(args.out.stem + "_placement.json")
    run_placement(args.device, families, placement_out)
    run_iteration(args, counts)
    sys.exit(report([placement_out, args.out], args.out.with_name(args.out.stem + "_report.json"),
                    None))  # fmt: skip


def check_device_argument(device: str) -> None:
    """Exit with one line unless ``--device`` names a device torch can use here."""
    if DEVICE_PATTERN.fullmatch(device) is None:
        sys.exit(f"error: --device: got {device!r}, allowed: cpu, cuda, cuda:N")
    problem = device_problem(device)
    if problem is not None:
        sys.exit(f"error: --device: {problem}")


def _run_warm_up(device: str, compiled: bool) -> None:
    """torch's (and, with ``compiled``, numba's) first calls, unmeasured."""
    run = _run(WARM_UP_AGENTS, device)
    indices = list(range(WARM_UP_AGENTS))
    group = make_agent_group(run, indices, variants_of(run, indices))
    group.train(1, initial_theta(variants_of(run, [0])[0], run), indices)
    if compiled:
        cpu = _run(WARM_UP_AGENTS, "cpu", engine="auto")
        group = make_agent_group(cpu, indices, variants_of(cpu, indices))
        group.train(1, initial_theta(variants_of(cpu, [0])[0], cpu), indices)


if __name__ == "__main__":
    main()
