"""How many agents one host trains on a torch device (algo.engine=torch, algo.device).

One agent host's round (CartPole variants of the population, a 16-16 MLP unless
``--hidden``, every agent training, the counted clock so nothing sleeps) on the engine, its
environments, policies and gradients in torch on ``--device``. K doubles from ``--start``
until a round takes longer than ``--max-round-s``, memory runs out, or K would pass
``--max-agents``; the largest K whose round ended is the figure. Up to ``--compare-up-to``
agents the same round also runs on the compiled backend (the CPU default for CartPole) on
this CPU: ratios measured in the same process. First, a placement check: whether an agent's
θ is bit-identical in any company and on a second run, on this device.

    python -m benchmarks.scale_device --device cuda      # make bench-device
    python -m benchmarks.scale_device --device cpu --start 100 --max-agents 400   # a smoke run
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from benchmarks.scale_refs import cpu_description
from fedhpg.common.config import DEVICE_PATTERN
from fedhpg.common.engine.devices import device_problem
from fedhpg.common.group import EngineGroup, make_agent_group
from fedhpg.common.runtime.cli import compose
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import initial_theta

logger = logging.getLogger("benchmarks.scale_device")

RESULTS = Path(__file__).parent / "results" / "scale_device.json"
OVERRIDES = ["env=cartpole", "agents=population", "agents.clock=counted"]
WARM_UP_AGENTS = 20
"""Agents of the round each engine runs first, unmeasured (torch's and numba's first calls)."""


@dataclass(frozen=True)
class Row:
    agents: int
    env_steps: int
    round_s: float
    steps_per_s: float
    compiled_round_s: float | None
    """The same round on the compiled engine, the CPU default for CartPole (None: not
    compared)."""
    device_peak_mib: float | None
    """torch's peak allocation on a CUDA device during the round (None on the CPU)."""
    host_peak_mib: float
    """This process's peak resident memory so far."""


def _round(agents: int, engine: str, device: str, hidden: int) -> tuple[int, float]:
    """(env steps, wall seconds) of round 1 of agents 0 … K−1, one host, from θ̃_0."""
    run = compose([*OVERRIDES, f"agents.num_agents={agents}", f"algo.engine={engine}",
                   f"algo.device={device}", f"policy.hidden=[{hidden},{hidden}]"])  # fmt: skip
    indices = list(range(agents))
    group = make_agent_group(run, indices, variants_of(run, indices))
    assert isinstance(group, EngineGroup)
    assert (group.engine.compiled is not None) == (engine == "auto" and device == "cpu")
    group.prepare()
    theta = initial_theta(variants_of(run, [0])[0], run)
    started = time.perf_counter()
    results = group.train(1, theta, indices)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    wall = time.perf_counter() - started
    return sum(r.stats.env_steps for r in results.values()), wall


def measure(device: str, start: int, max_agents: int, max_round_s: float,
            compare_up_to: int, hidden: int = 16) -> tuple[list[Row], str]:  # fmt: skip
    """The rows up to the largest K reached, and why the doubling stopped."""
    cuda = device.startswith("cuda")
    _round(WARM_UP_AGENTS, "torch", device, hidden)
    try:  # numba compiles the kernels on a machine whose cache is empty
        _round(WARM_UP_AGENTS, "auto", "cpu", hidden)
        compiled = True
    except Exception as error:  # e.g. a numba that does not support this numpy
        logger.warning("the compiled engine cannot run here, not compared: %s", error)
        compiled = False
    rows: list[Row] = []
    agents = start
    while agents <= max_agents:
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        try:
            steps, wall = _round(agents, "torch", device, hidden)
        except (torch.OutOfMemoryError, MemoryError) as error:
            return rows, f"K = {agents:,}: out of memory ({type(error).__name__})"
        compared = agents <= compare_up_to
        compiled_s = _round(agents, "auto", "cpu", hidden)[1] if compared and compiled else None
        rows.append(Row(
            agents=agents,
            env_steps=steps,
            round_s=wall,
            steps_per_s=steps / wall,
            compiled_round_s=compiled_s,
            device_peak_mib=torch.cuda.max_memory_allocated() / 2**20 if cuda else None,
            host_peak_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        ))  # fmt: skip
        logger.info("K = %d: %.2f s a round, %.3g steps/s", agents, wall, steps / wall)
        if wall > max_round_s:
            return rows, f"K = {agents:,}: a round took {wall:.0f} s > --max-round-s"
        agents *= 2
    return rows, f"K would pass --max-agents = {max_agents:,}"


def placement_check(device: str, hidden: int) -> dict[str, bool]:
    """Whether, on ``device``, an agent's θ after a round is bit-identical in any company
    (alone, in small groups, all nine together) and on a second run."""
    run = compose([*OVERRIDES, "agents.num_agents=9", "algo.engine=torch",
                   f"algo.device={device}", f"policy.hidden=[{hidden},{hidden}]"])  # fmt: skip
    theta = initial_theta(variants_of(run, [0])[0], run)

    def train(company: list[int]) -> dict[int, torch.Tensor]:
        group = make_agent_group(run, company, variants_of(run, company))
        assert isinstance(group, EngineGroup)
        return {k: r.theta for k, r in group.train(3, theta, company).items()}

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


def table(rows: list[Row]) -> str:
    lines = ["| K | env steps | round (s) | steps/s | compiled (s) | torch / compiled "
             "| device peak (MiB) | host peak (MiB) |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip

    def cell(value: float | None, digits: int = 2) -> str:
        return "—" if value is None else f"{value:.{digits}f}"

    for r in rows:
        vs_compiled = r.round_s / r.compiled_round_s if r.compiled_round_s else None
        lines.append(f"| {r.agents:,} | {r.env_steps:,} | {r.round_s:.2f} | {r.steps_per_s:.3g} "
                     f"| {cell(r.compiled_round_s)} | {cell(vs_compiled)} "
                     f"| {cell(r.device_peak_mib, 0)} | {r.host_peak_mib:.0f} |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--start", type=int, default=1000)
    parser.add_argument("--max-agents", type=int, default=256_000)
    parser.add_argument("--max-round-s", type=float, default=60.0)
    parser.add_argument("--compare-up-to", type=int, default=8000)
    parser.add_argument("--hidden", type=int, default=16, help="units of each of the 2 layers")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.start < 1 or args.max_agents < args.start or args.hidden < 1:
        sys.exit("error: need 1 <= --start <= --max-agents and --hidden >= 1")
    if DEVICE_PATTERN.fullmatch(args.device) is None:
        sys.exit(f"error: --device: got {args.device!r}, allowed: cpu, cuda, cuda:N")
    problem = device_problem(args.device)
    if problem is not None:
        sys.exit(f"error: --device: {problem}")
    torch.set_num_threads(1)
    placement = placement_check(args.device, args.hidden)
    rows, stopped = measure(args.device, args.start, args.max_agents, args.max_round_s,
                            args.compare_up_to, args.hidden)  # fmt: skip
    name = torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else "CPU"
    largest = rows[-1].agents if rows else 0
    print(f"device: {name}; host CPU: {cpu_description()}; MLP {args.hidden}-{args.hidden}")
    print(table(rows))
    print(f"largest K reached: {largest:,} (stopped: {stopped})")
    print("placement check (9 agents, round 3): " + ", ".join(
        f"{name.replace('_', ' ')}: {'yes' if held else 'NO'}" for name, held in placement.items()
    ))  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "device": args.device, "device_name": name, "machine": cpu_description(),
        "hidden": args.hidden, **placement,
        "largest_agents": largest, "stopped": stopped, "rows": [asdict(r) for r in rows],
    }, indent=1) + "\n")  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
