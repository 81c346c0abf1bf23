"""The compiled engine of this working tree against the one of an earlier commit, interleaved
in one process: what a change to the kernels costs or saves, and whether it moves θ.

The earlier commit's ``common/batched/kernels.py`` and ``compiled.py`` are taken with
``git show`` into a scratch package (numba caches their code there, so a second run against
the same commit compiles nothing), and one host's agents of ``make bench-scale``'s K = 1,000
case train a round through each engine in turn, from the same θ, round after round, the
order alternating. Each pair is measured under the same machine conditions, so the paired
ratio (this tree / the commit's) is the figure; a single run of each, minutes apart, wanders
by more than the changes it would judge. Sampling and the gradient-and-step phase are timed
apart (CPU time, ``engine_sample_s`` / ``engine_gradient_s``) and divided by the round's env
steps (a change that moves θ changes the episodes, and so the work), and every round's θ of
the two engines is compared bit for bit. Each order is taken equally often (an odd ``--rounds``
is rounded up): whichever engine runs second in a pair may find the caches warmer. Against
``HEAD`` with no change in the tree, it measures its own noise floor.

    python -m benchmarks.kernels_ab --against HEAD [--rounds 15] [--theta trained.pt]
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

from benchmarks.scale_engine import HOST, OVERRIDES, start_theta
from fedhpg.common.batched import batched_group_or_none
from fedhpg.common.batched.compiled import CompiledFedHPG
from fedhpg.common.runtime.cli import compose
from fedhpg.common.variants import variants_of

log = logging.getLogger(__name__)

KERNELS_IMPORT = "from fedhpg.common.batched import kernels\n"
"""The line by which ``compiled.py`` takes its kernels; the commit's copy takes its own."""


def engine_module(revision: str) -> ModuleType:
    """``compiled.py`` of ``revision``, bound to that revision's ``kernels.py``."""
    repo = Path(__file__).resolve().parents[1]

    def git(*args: str) -> subprocess.CompletedProcess[str]:
        try:
            return subprocess.run(["git", *args], cwd=repo, text=True, capture_output=True)
        except OSError as error:
            raise SystemExit(f"kernels_ab: cannot run git: {error}") from None

    def show(path: str) -> str:
        shown = git("show", f"{revision}:{path}")
        if shown.returncode:
            raise SystemExit(f"kernels_ab: no {path} at {revision!r}: {shown.stderr.strip()}")
        return shown.stdout

    sha = git("rev-parse", "--short=12", revision).stdout.strip() or revision
    name = f"fedhpg_kernels_ab_{sha}"
    compiled_source = show("common/batched/compiled.py")
    kernels_source = show("common/batched/kernels.py")
    if KERNELS_IMPORT not in compiled_source:
        raise SystemExit(f"kernels_ab: {revision}'s compiled.py does not import its kernels "
                         f"as {KERNELS_IMPORT.strip()!r}")  # fmt: skip
    folder = Path(tempfile.gettempdir()) / "fedhpg-kernels-ab" / sha
    folder.mkdir(parents=True, exist_ok=True)
    for file, text in (
        ("kernels.py", kernels_source),
        ("compiled.py", compiled_source.replace(KERNELS_IMPORT, f"import {name}_k as kernels\n")),
    ):
        target = folder / file
        if not target.exists() or target.read_text() != text:  # unchanged: numba's cache holds
            target.write_text(text)
    modules = {}
    for suffix, file in (("_k", "kernels.py"), ("", "compiled.py")):
        spec = importlib.util.spec_from_file_location(name + suffix, folder / file)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name + suffix] = module
        spec.loader.exec_module(module)
        modules[suffix] = module
    return modules[""]


@dataclass(frozen=True)
class Comparison:
    rounds: int
    sampling: float
    """Median over rounds of this tree's sampling CPU per env step / the commit's (per step:
    where θ differs, so do the episodes and their lengths)."""
    gradient: float
    """The same for the estimator, gradient and step."""
    whole: float
    this_ns: tuple[float, float]
    """This tree's sampling and gradient CPU per env step (ns, medians)."""
    that_ns: tuple[float, float]
    steps: tuple[float, float]
    """Env steps per round, this tree's and the commit's (medians)."""
    identical_rounds: int
    largest_difference: float
    """The largest |θ_this − θ_that| over all agents and rounds."""


def compare(revision: str, rounds: int, theta: torch.Tensor) -> Comparison:
    run = compose(OVERRIDES)
    agents = list(range(HOST))
    variants = variants_of(run, agents)
    this = batched_group_or_none(run, variants)
    assert isinstance(this, CompiledFedHPG)
    engines = {
        "this": this,
        "that": engine_module(revision).CompiledFedHPG(run, variants, this.shape),
    }
    for engine in engines.values():
        engine.prepare()
    times: dict[str, list[tuple[float, float]]] = {"this": [], "that": []}  # s per env step
    steps: dict[str, list[int]] = {"this": [], "that": []}
    identical, largest = 0, 0.0
    for r in range(rounds + 1):  # round 0 compiles or loads the kernels, and is dropped
        thetas = {}
        for name in ("this", "that") if r % 2 else ("that", "this"):
            trained = engines[name].train_columns(r, theta, agents)
            thetas[name] = trained.thetas.copy()
            sample = sum(v or 0.0 for v in trained.algorithm["engine_sample_s"])
            gradient = sum(v or 0.0 for v in trained.algorithm["engine_gradient_s"])
            count = max(int(trained.env_steps.sum()), 1)
            if r:
                times[name].append((sample / count, gradient / count))
                steps[name].append(count)
        if r:
            identical += bool(np.array_equal(thetas["this"], thetas["that"]))
            largest = max(largest, float(np.abs(thetas["this"] - thetas["that"]).max()))
        log.info("round %d/%d", r, rounds)

    def paired(phase: int | None) -> float:
        def cost(pair: tuple[float, float]) -> float:
            return sum(pair) if phase is None else pair[phase]

        return statistics.median(
            cost(a) / cost(b) for a, b in zip(times["this"], times["that"], strict=True)
        )

    def medians(name: str) -> tuple[float, float]:
        sample, gradient = (1e9 * statistics.median(t[i] for t in times[name]) for i in (0, 1))
        return sample, gradient

    return Comparison(
        rounds=rounds,
        sampling=paired(0),
        gradient=paired(1),
        whole=paired(None),
        this_ns=medians("this"),
        that_ns=medians("that"),
        steps=(statistics.median(steps["this"]), statistics.median(steps["that"])),
        identical_rounds=identical,
        largest_difference=largest,
    )


def report(revision: str, c: Comparison) -> str:
    return "\n".join([
        f"this tree against {revision}: {HOST} agents, {c.rounds} interleaved rounds, "
        f"{c.steps[0]:,.0f} against {c.steps[1]:,.0f} env steps a round (medians)",
        f"  sampling CPU            {c.this_ns[0]:6.1f} ns against {c.that_ns[0]:6.1f} ns a step: "
        f"paired median ratio {c.sampling:.3f}",
        f"  gradient-and-step CPU   {c.this_ns[1]:6.1f} ns against {c.that_ns[1]:6.1f} ns a step: "
        f"paired median ratio {c.gradient:.3f}",
        f"  both                    paired median ratio {c.whole:.3f}",
        f"  θ bit-identical in {c.identical_rounds} of {c.rounds} rounds; largest difference "
        f"{c.largest_difference:.3g}",
    ])  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--against", default="HEAD", help="the commit to compare with")
    parser.add_argument("--rounds", type=int, default=15, help="interleaved rounds (≥ 1)")
    parser.add_argument("--theta", help="start every round from this θ (torch-saved .pt)")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    args.rounds += args.rounds % 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    try:
        theta = torch.load(args.theta) if args.theta else start_theta()
    except (OSError, RuntimeError) as error:
        parser.error(f"--theta {args.theta}: {error}")
    if not isinstance(theta, torch.Tensor) or theta.dim() != 1:
        parser.error(f"--theta {args.theta}: not a flat θ (a torch-saved 1-D tensor)")
    print(report(args.against, compare(args.against, args.rounds, theta)))


if __name__ == "__main__":
    main()
