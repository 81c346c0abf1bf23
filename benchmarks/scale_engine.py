"""The compiled engine against reference (b), interleaved in one process: ``make bench-scale``'s
cross-check of its sampling ratio.

A federation's figures and the references it is compared with are measured a minute apart,
and on a shared machine one measurement of (b) wanders by ±30 % between runs. Here one host's
agents of the population (the same copies as (b)) sample one local iteration and take its
gradients and steps through the engine's kernels, then (b) steps the same copies, over and
over: the ratio of each such pair is measured under the same conditions, and the median of
the pairs is the figure. At θ̃_0 (episodes of ~20 steps) and at a trained θ̃ (~500).

    python -m benchmarks.scale_engine [--theta checkpoint-or-.pt]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass

import numpy as np
import torch

from benchmarks.scale_refs import forward_loop
from fedhpg.common.batched import batched_group_or_none, kernels
from fedhpg.common.batched.compiled import CompiledFedHPG, _RowBuffers
from fedhpg.common.batched.streams import agent_streams
from fedhpg.common.runtime.cli import compose
from fedhpg.common.variants import variants_of
from fedhpg.common.worker import Stream, initial_theta

OVERRIDES = ["env=cartpole", "agents=population", "agents.num_agents=1000",
             "policy.hidden=[16,16]", "agents.clock=counted"]  # fmt: skip
HOST = 500
"""One host's agents of bench-scale's K = 1,000 case (agents 0-499)."""


@dataclass(frozen=True)
class EngineRatios:
    label: str
    steps_per_iteration: int
    sampling_vs_b: float
    """Median over pairs of (env steps per second of the sampling kernel) / (b)."""
    sampling_and_learning_vs_b: float
    """The same with the estimator, gradient and step kernel's time added."""
    b_median: float
    pairs: int


def measure(theta: torch.Tensor, label: str, pairs: int = 8) -> EngineRatios:
    run = compose(OVERRIDES)
    indices = list(range(HOST))
    engine = batched_group_or_none(run, variants_of(run, indices))
    assert isinstance(engine, CompiledFedHPG)
    batch = np.array([engine.budget(k).batch_size for k in indices], dtype=np.int64)
    horizons, gammas, physics = engine._per_agent(indices)
    thetas = np.repeat(theta.numpy().astype(np.float32)[None], HOST, 0)
    rows = _RowBuffers(int((batch * np.minimum(horizons, 500)).sum()), 4)
    span = np.zeros((HOST, 2), dtype=np.int64)
    copy_start = np.zeros(HOST, dtype=np.int64)
    lengths = np.zeros(int(batch.sum()), dtype=np.int64)
    returns = np.zeros(int(batch.sum()))
    agents = np.arange(HOST)
    no_rows = np.zeros((0, thetas.shape[1]), dtype=np.float32)
    sampling, both, references = [], [], []
    for pair in range(pairs + 1):  # the first pair warms up, and is dropped
        streams = agent_streams(run.seed, indices, pair, int(Stream.TRAIN))
        started = time.perf_counter()
        kernels.sample_iteration(thetas, engine.sizes, physics, batch, horizons, gammas, streams,
                                 agents, rows.obs, rows.action, rows.copy, rows.time, span,
                                 copy_start, lengths, returns)  # fmt: skip
        sampled = time.perf_counter()
        kernels.learn_iteration(thetas.copy(), np.zeros_like(thetas), np.zeros_like(thetas),
                                engine.sizes, batch, gammas, np.zeros(HOST, dtype=np.int64),
                                agents, rows.obs, rows.action, rows.copy, rows.time, rows.coef,
                                span, copy_start, lengths, engine.options, 1.0, -1.0,
                                np.zeros(HOST, dtype=np.bool_), np.zeros(HOST, dtype=np.bool_),
                                no_rows, np.zeros(HOST, dtype=np.int64), no_rows)  # fmt: skip
        learned = time.perf_counter()
        reference = forward_loop(batch.tolist(), (16, 16), 200)
        if pair:
            steps = int(lengths.sum())
            sampling.append(steps / (sampled - started) / reference)
            both.append(steps / (learned - started) / reference)
            references.append(reference)
    return EngineRatios(
        label=label,
        steps_per_iteration=int(lengths.sum()),
        sampling_vs_b=statistics.median(sampling),
        sampling_and_learning_vs_b=statistics.median(both),
        b_median=statistics.median(references),
        pairs=pairs,
    )


def start_theta() -> torch.Tensor:
    run = compose(OVERRIDES)
    return initial_theta(variants_of(run, [0])[0], run)


def table(results: list[EngineRatios]) -> str:
    lines = [
        "| θ̃ | env steps per iteration (500 agents) | sampling vs (b) | sampling + gradients "
        "and steps vs (b) | (b) (M/s, median) | pairs |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r.label} | {r.steps_per_iteration:,} | {r.sampling_vs_b:.2f} | "
            f"{r.sampling_and_learning_vs_b:.2f} | {r.b_median / 1e6:.2f} | {r.pairs} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--theta", help="a trained θ̃: a torch-saved tensor (.pt)")
    args = parser.parse_args()
    results = [measure(start_theta(), "θ̃_0")]
    if args.theta:
        results.append(measure(torch.load(args.theta), "trained"))
    print(table(results))


if __name__ == "__main__":
    main()
