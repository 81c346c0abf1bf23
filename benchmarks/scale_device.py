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
  process's peak resident memory, malloc's large blocks returned) beside the memory plan's;
- the reference (:mod:`benchmarks.device_reference`: K × 16 copies, 64 steps with auto-reset,
  sampling alone and with its REINFORCE gradient and step), and up to ``--compare-up-to``
  agents the same round on the compiled engine on this machine's CPU.

First, the placement check: whether an agent's θ after 3 rounds is bit-identical alone, in four
companies and on a second run, on the device, for CartPole, GridWorld (the environment's own
draws) and Pendulum (a Gaussian policy).

    python -m benchmarks.scale_device --device cuda            # make bench-device
    python -m benchmarks.scale_device --device cpu --agents 100,1000 --repeats 2   # rehearsal
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from benchmarks.device_reference import measure as reference
from benchmarks.scale_refs import cpu_description
from fedhpg.common.config import DEVICE_PATTERN, RunConfig
from fedhpg.common.engine.devices import device_problem
from fedhpg.common.group import EngineGroup, make_agent_group
from fedhpg.common.policies import get_flat_params
from fedhpg.common.runtime.cli import compose
from fedhpg.common.runtime.memory import pin_malloc_mmap_threshold
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import build_policy, initial_theta

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
    peak resident memory lies above its resident memory before them (malloc's large blocks
    are returned on free, so resident memory follows what lives)."""
    planned_peak_mib: float
    chunks: int
    compiled_steps_per_s: float | None
    """The same round on the compiled engine on this machine's CPU (None: not compared)."""


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


def _peak_rss() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _rss() -> int:
    """This process's resident memory now."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * resource.getpagesize()


def iterations(group: EngineGroup, theta: torch.Tensor, agents: list[int], device: str,
               repeats: int) -> tuple[int, float, float | None]:  # fmt: skip
    """(env steps of one iteration, median seconds, peak MiB) over ``repeats`` rounds after an
    unmeasured one."""
    cuda = device.startswith("cuda")
    before = _rss()  # the unmeasured round's peak counts too: it is the same round
    group.train(1, theta, agents)
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)
    times, steps = [], []
    for repeat in range(repeats):
        _sync(device)
        started = time.perf_counter()
        results = group.train(2 + repeat, theta, agents)
        _sync(device)
        times.append(time.perf_counter() - started)
        steps.append(sum(r.stats.env_steps for r in results.values()))
    peak = torch.cuda.max_memory_allocated(device) if cuda else _peak_rss() - before
    middle = sorted(range(repeats), key=times.__getitem__)[repeats // 2]
    return steps[middle], times[middle], peak / MIB


def measure_engine(agents: int, device: str, repeats: int, compare: bool,
                   max_iteration_s: float) -> list[Row]:  # fmt: skip
    run = _run(agents, device)
    indices = list(range(agents))
    group = make_agent_group(run, indices, variants_of(run, indices))
    assert isinstance(group, EngineGroup) and group.engine.compiled is None
    group.prepare()
    plan = group.plan(indices)
    compiled_group = None
    if compare:
        cpu = _run(agents, "cpu", engine="auto")
        compiled_group = make_agent_group(cpu, indices, variants_of(cpu, indices))
        assert isinstance(compiled_group, EngineGroup) and compiled_group.engine.compiled
        compiled_group.prepare()
    rows = []
    for name, theta in (("initial", initial_theta(variants_of(run, [0])[0], run)),
                        ("balancing", balancing_theta(run))):  # fmt: skip
        steps, seconds, peak = iterations(group, theta, indices, device, repeats)
        compiled = None
        if compiled_group is not None:
            c_steps, c_seconds, _ = iterations(compiled_group, theta, indices, "cpu", repeats)
            compiled = c_steps / c_seconds
        rows.append(Row(
            agents=agents, policy=name, env_steps=steps, iteration_s=seconds,
            steps_per_s=steps / seconds, device_peak_mib=peak,
            planned_peak_mib=plan.peak_bytes / MIB, chunks=len(plan.chunks),
            compiled_steps_per_s=compiled,
        ))  # fmt: skip
        logger.info("K = %d, %s: %.3g s an iteration, %.3g steps/s, peak %.0f MiB",
                    agents, name, seconds, steps / seconds, peak or 0.0)  # fmt: skip
        if seconds > max_iteration_s:
            logger.warning("K = %d: an iteration took %.0f s > --max-iteration-s: the "
                           "balancing policy is not measured", agents, seconds)  # fmt: skip
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
}


def placement_check(device: str) -> dict[str, bool]:
    """Whether, on ``device``, an agent's θ after round 3 is bit-identical in any company
    (alone, in small groups, all nine together) and on a second run, for each family of
    :data:`PLACEMENT_FAMILIES` (population budgets: rows of different batch sizes)."""
    held = {"same_theta_in_any_company": True, "same_theta_on_a_second_run": True}
    for overrides in PLACEMENT_FAMILIES.values():
        run = compose([*overrides, "agents=population", "agents.num_agents=9",
                       "algo.engine=torch", f"algo.device={device}"])  # fmt: skip
        theta = initial_theta(variants_of(run, [0])[0], run)

        def train(company: list[int]) -> dict[int, torch.Tensor]:
            group = make_agent_group(run, company, variants_of(run, company))  # noqa: B023
            assert isinstance(group, EngineGroup)
            return {k: r.theta for k, r in group.train(3, theta, company).items()}  # noqa: B023

        everyone = train(list(range(9)))
        companies = [train(c) for c in ([4], [8, 0], [7, 2, 5], [6, 1, 3, 0, 8, 2, 4])]
        held["same_theta_in_any_company"] &= all(
            torch.equal(got[k], everyone[k]) for got in companies for k in got
        )
        held["same_theta_on_a_second_run"] &= all(
            torch.equal(got, everyone[k]) for k, got in train(list(range(9))).items()
        )
    return held


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
        ref = refs[r.agents]
        lines.append(
            f"| {r.agents:,} | {r.policy} | {r.env_steps:,} | {r.iteration_s:.3f} "
            f"| {r.steps_per_s / 1e6:.3g} | {ref.sampling_steps_per_s / 1e6:.3g} "
            f"| {ref.with_gradient_steps_per_s / 1e6:.3g} "
            f"| {r.steps_per_s / ref.with_gradient_steps_per_s:.2f} "
            f"| {_cell(r.device_peak_mib, digits=0)} | {r.planned_peak_mib:,.0f} | {r.chunks} "
            f"| {_cell(ref.peak_mib, digits=0)} | {_cell(r.compiled_steps_per_s, 1e6)} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--agents", default="1000,16000,65536",
                        help="comma-separated K to measure")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--compare-up-to", type=int, default=1000)
    parser.add_argument("--max-iteration-s", type=float, default=60.0,
                        help="skip the balancing policy after a slower first one")  # fmt: skip
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    try:
        counts = [int(k) for k in args.agents.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1 or args.repeats < 1:
        sys.exit("error: need --agents as positive integers (1000,16000) and --repeats >= 1")
    if DEVICE_PATTERN.fullmatch(args.device) is None:
        sys.exit(f"error: --device: got {args.device!r}, allowed: cpu, cuda, cuda:N")
    problem = device_problem(args.device)
    if problem is not None:
        sys.exit(f"error: --device: {problem}")
    torch.set_num_threads(1)
    pin_malloc_mmap_threshold()  # large blocks returned on free: resident memory is live memory
    started = time.perf_counter()
    placement = placement_check(args.device)
    logger.info("placement check: %s", placement)
    _run_warm_up(args.device)
    rows: list[Row] = []
    refs: dict[int, ReferenceRow] = {}
    for agents in sorted(counts):
        refs[agents] = measure_reference(agents, args.device, args.repeats)
        rows += measure_engine(agents, args.device, args.repeats,
                               agents <= args.compare_up_to, args.max_iteration_s)  # fmt: skip
    name = torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else "CPU"
    print(f"device: {name}; host CPU: {cpu_description()}; CartPole, MLP 16-16, B = {BATCH}")
    print(table(rows, refs))
    print("placement check (9 agents, round 3; cartpole, gridworld, pendulum): " + ", ".join(
        f"{key.replace('_', ' ')}: {'yes' if held else 'NO'}" for key, held in placement.items()
    ))  # fmt: skip
    largest = max(counts)
    at_largest = [r for r in rows if r.agents == largest]
    if at_largest:
        best = max(r.steps_per_s for r in at_largest)
        ratio = best / refs[largest].with_gradient_steps_per_s
        print(f"K = {largest:,}: engine {best / 1e6:.3g} M steps/s with gradients, "
              f"{ratio:.2f} × the reference with its gradient")  # fmt: skip
    elapsed = time.perf_counter() - started
    print(f"bench-device took {elapsed:.0f} s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "device": args.device, "device_name": name, "machine": cpu_description(),
        "torch": torch.__version__, "batch": BATCH, "seconds": elapsed, **placement,
        "rows": [asdict(r) for r in rows],
        "reference": [asdict(r) for r in refs.values()],
        "median_engine_over_reference": statistics.median(
            r.steps_per_s / refs[r.agents].with_gradient_steps_per_s for r in rows
        ) if rows else None,
    }, indent=1) + "\n")  # fmt: skip
    print(f"wrote {args.out}")


def _run_warm_up(device: str) -> None:
    """torch's (and numba's) first calls, unmeasured."""
    run = _run(WARM_UP_AGENTS, device)
    indices = list(range(WARM_UP_AGENTS))
    group = make_agent_group(run, indices, variants_of(run, indices))
    group.train(1, initial_theta(variants_of(run, [0])[0], run), indices)
    cpu = _run(WARM_UP_AGENTS, "cpu", engine="auto")
    compiled = make_agent_group(cpu, indices, variants_of(cpu, indices))
    compiled.train(1, initial_theta(variants_of(cpu, [0])[0], cpu), indices)


if __name__ == "__main__":
    main()
