"""Where one local iteration's time goes on a device: ``make bench-device``'s profile part.

The same round as :mod:`benchmarks.scale_device` (K CartPole agents, 16-16 MLP, B = 16, one
local iteration on the torch engine), at θ̃₀ and at the balancing policy. After an unmeasured
round, the same round three times: plain (the iteration's time), then

- by section: the engine's sampling, the estimator's coefficients, and the gradient pass's
  three parts (cutting the steps into tiles, the tiles' gradients, their sums per row), each
  timed between device synchronisations; "the rest" is the round's time outside them (the
  step, the statistics, θ to and from the device);
- by operator: under torch's profiler, the operators that took the most device time (the
  CPU's own time on the CPU), with their call counts.

    python -m benchmarks.device_profile --device cuda --agents 16000
    python -m benchmarks.device_profile --device cpu --agents 200      # the rehearsal
"""

from __future__ import annotations

import argparse
import inspect
import logging
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks.scale_device import (
    _header,
    _run,
    _sync,
    _write,
    balancing_theta,
    check_device_argument,
    timed_round,
)
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.batched.backend import CompiledBackend
from fedhpg.common.learning.engine.torch_backend import TorchBackend
from fedhpg.common.learning.group import EngineGroup, make_agent_group
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.memory import tune_malloc_for_engine

logger = logging.getLogger("benchmarks.device_profile")

RESULTS = Path(__file__).parent / "results" / "device_profile.json"
SECTIONS = {
    "sampling": "sample",
    "estimator": "coefficients",
    "tiles": "_tiles",
    "tile gradients": "_tile_gradients",
    "row sums": "_group_sums",
}
"""Section name → the :class:`TorchBackend` method it times (none of them calls another)."""
TOP = 20


@contextmanager
def timed_sections(device: str, seconds: dict[str, float]) -> Iterator[None]:
    """Inside, every call of a :data:`SECTIONS` method adds its time, between device
    synchronisations, to ``seconds[section]``; the methods are restored after."""
    saved: dict[str, Any] = {}

    def timer(section: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            _sync(device)
            started = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                _sync(device)
                seconds[section] = seconds.get(section, 0.0) + time.perf_counter() - started

        return call

    for section, name in SECTIONS.items():
        static = inspect.getattr_static(TorchBackend, name)
        saved[name] = static
        if isinstance(static, staticmethod):
            setattr(TorchBackend, name, staticmethod(timer(section, static.__func__)))
        else:
            setattr(TorchBackend, name, timer(section, static))
    try:
        yield
    finally:
        for name, static in saved.items():
            setattr(TorchBackend, name, static)


def top_operators(
    device: str, run_round: Callable[[], object]
) -> tuple[str, list[dict[str, object]]]:
    """The :data:`TOP` operators of one ``run_round()`` by their own device time (the CPU's
    own time on the CPU, or where the profiler saw no device time: a CUDA build without
    CUPTI): what they are ranked by ("device" or "cpu"), and each one's name, calls and
    seconds."""
    cuda = device.startswith("cuda")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        run_round()
    events = prof.key_averages()

    def on_device(event: Any) -> float:
        return float(getattr(event, "self_device_time_total", 0.0) or 0.0)

    def on_cpu(event: Any) -> float:
        return float(event.self_cpu_time_total)

    by, own = ("device", on_device) if cuda else ("cpu", on_cpu)
    if cuda and not any(on_device(e) > 0 for e in events):
        logger.warning("the profiler saw no device time: operators ranked by CPU time")
        by, own = "cpu", on_cpu
    ranked = sorted(events, key=own, reverse=True)[:TOP]
    return by, [
        {"operator": e.key, "calls": int(e.count), "seconds": own(e) / 1e6}
        for e in ranked
        if own(e) > 0
    ]


def profile_round(agents: int, device: str, name: str) -> dict[str, object]:
    """One policy's sections and top operators at K = ``agents``."""
    run = _run(agents, device)
    indices = list(range(agents))
    group = make_agent_group(run, indices, variants_of(run, indices))
    assert isinstance(group, EngineGroup)
    assert not isinstance(group.engine.backend, CompiledBackend)
    group.prepare()
    theta = (
        initial_theta(variants_of(run, [0])[0], run) if name == "initial" else balancing_theta(run)
    )
    timed_round(group, theta, indices, device, 1)  # unmeasured: first calls, the allocator's pools
    plain, steps = timed_round(group, theta, indices, device, 2)
    seconds: dict[str, float] = {}
    with timed_sections(device, seconds):
        sectioned, _ = timed_round(group, theta, indices, device, 2)
    try:
        ranked_by, operators = top_operators(
            device, lambda: timed_round(group, theta, indices, device, 2)
        )
    except RuntimeError as error:  # the sections stand without the operators
        logger.warning("torch's profiler failed (%s): no operator table", error)
        ranked_by, operators = "none", []
    group.close()
    timed = sum(seconds.values())
    return {
        "agents": agents,
        "policy": name,
        "env_steps": steps,
        "iteration_s": plain,
        "sectioned_iteration_s": sectioned,
        "sections_s": {**seconds, "the rest": max(sectioned - timed, 0.0)},
        "operators_ranked_by": ranked_by,
        "top_operators": operators,
    }


def table(entry: dict[str, Any]) -> str:
    """One profiled round as two small tables (sections; top operators)."""
    steps, sectioned = entry["env_steps"], entry["sectioned_iteration_s"]
    lines = [
        f"K = {entry['agents']:,}, {entry['policy']}: {steps:,} env steps, "
        f"{entry['iteration_s']:.3f} s an iteration ({sectioned:.3f} s with the sections timed)",
        "| section | s | share | ns per env step |",
        "|---|---|---|---|",
    ]
    for section, value in entry["sections_s"].items():
        lines.append(
            f"| {section} | {value:.3f} | {value / max(sectioned, 1e-12):.0%} "
            f"| {1e9 * value / max(steps, 1):.1f} |"
        )
    lines += [f"| operator | calls | s (own, {entry['operators_ranked_by']}) |", "|---|---|---|"]
    for op in entry["top_operators"]:
        lines.append(f"| {op['operator']} | {op['calls']:,} | {op['seconds']:.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--agents", type=int, default=16000)
    parser.add_argument("--policies", default="initial,balancing",
                        help="comma-separated: initial (θ̃₀), balancing")  # fmt: skip
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    policies = args.policies.split(",")
    if args.agents < 1 or not set(policies) <= {"initial", "balancing"}:
        sys.exit("error: need --agents >= 1 and --policies from initial,balancing")
    check_device_argument(args.device)
    torch.set_num_threads(1)
    tune_malloc_for_engine()  # as an engine's agent process runs (benchmarks/scale_device.py)
    record: dict[str, object] = {"part": "profile", **_header(args.device), "rounds": []}
    for name in policies:
        entry = profile_round(args.agents, args.device, name)
        record["rounds"].append(entry)  # type: ignore[attr-defined]
        _write(args.out, record)
        print(table(entry), flush=True)
    logger.info("wrote %s", args.out)


if __name__ == "__main__":
    main()
