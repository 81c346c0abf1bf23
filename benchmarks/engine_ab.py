"""This tree's agent groups against an earlier commit's, interleaved: what a change to the
engine costs or saves, measured under the same machine conditions.

The commit's package is taken with ``git archive`` into a cache folder (numba's cache lives
beside it, so a second run against the same commit compiles nothing), and one process per
side (:mod:`benchmarks.engine_ab_worker`, importing only what every revision has:
``make_agent_group`` and the config) trains one host's agents a round at a time from the same
θ, the two sides alternating, round after round, the order swapped every pair. Each pair is
measured minutes apart from no other, so the paired ratio of env steps per second (this tree
over the commit) is the figure: two runs minutes apart wander by more than the changes they
would judge. Randomness differs between revisions, so the episodes and their work differ too;
hence steps per second, not seconds per round.

    python -m benchmarks.engine_ab --against 97553d4 [--algo fedhpgvr] [--agents 1000] \
        [--theta balancing]
    python -m benchmarks.engine_ab --tables-only

Each comparison is kept in ``benchmarks/results/engine_ab.json`` (one per algorithm, K and θ,
the last run of each), and the result table ``benchmarks/results/tables/engine_ab.json`` is
rebuilt from it: every comparison against :data:`BASELINE`. ``--tables-only`` rebuilds it
without running, stamped with the date, commit and machine of the stored measurement.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import tomllib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from benchmarks import results_file

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).with_name("engine_ab_worker.py")
BASELINE = "97553d4"
"""The last commit with a copy of the algorithm per backend (the per-agent loop, the compiled
FedHPG); ``make bench-scale`` compares against it."""
RESULTS = Path(__file__).parent / "results" / "engine_ab.json"


def _git(*args: str) -> subprocess.CompletedProcess[bytes]:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True)
    except OSError as error:
        raise SystemExit(f"engine_ab: cannot run git: {error}") from None


def checkout(revision: str) -> Path:
    """A folder whose ``fedhpg`` package is ``revision``'s tree."""
    sha = _git("rev-parse", "--short=12", f"{revision}^{{commit}}")
    if sha.returncode:
        raise SystemExit(f"engine_ab: no commit {revision!r} in this clone "
                         f"({sha.stderr.decode().strip() or 'git rev-parse failed'})")  # fmt: skip
    name = sha.stdout.decode().strip()
    folder = Path(tempfile.gettempdir()) / "fedhpg-engine-ab" / name
    package = folder / "fedhpg"
    if not (package / "common").is_dir():
        archive = _git("archive", "--format=tar", name)
        if archive.returncode:
            raise SystemExit(f"engine_ab: git archive {name}: {archive.stderr.decode().strip()}")
        package.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile() as raw:
            raw.write(archive.stdout)
            raw.seek(0)
            with tarfile.open(fileobj=raw) as tar:
                tar.extractall(package, filter="data")
    return folder


@dataclass(frozen=True)
class Tree:
    """What starts one side's federation."""

    label: str
    command: list[str] | None
    """None: this environment's ``fedhpg-run``."""
    env: dict[str, str]


def baseline_tree(revision: str) -> Tree:
    """``revision``'s own ``fedhpg-run``, its package alone on the path (checked)."""
    folder = checkout(revision)
    scripts = tomllib.loads((folder / "fedhpg" / "pyproject.toml").read_text())["project"]
    module, function = scripts["scripts"]["fedhpg-run"].split(":")
    env = {"PYTHONPATH": str(folder)}
    where = subprocess.run(
        [sys.executable, "-P", "-c", f"import {module} as m; print(m.__file__)"],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
    )
    if where.returncode or folder not in Path(where.stdout.strip()).parents:
        raise SystemExit(
            f"engine_ab: {revision}'s {module} did not import from {folder}: "
            f"{(where.stderr or where.stdout).strip()[-300:]}"
        )
    # -P: the working folder (this tree's, say) is not put before the commit's package
    command = [sys.executable, "-P", "-c", f"import sys; from {module} import {function}; "
               f"sys.exit({function}())"]  # fmt: skip
    return Tree(revision, command, env)


THIS_TREE = Tree("this tree", None, {})
"""This environment's own ``fedhpg-run``."""


@dataclass(frozen=True)
class Setup:
    """What both sides run."""

    against: str = BASELINE
    algo: str = "fedhpg"
    agents: int = 500
    rounds: int = 10
    """Interleaved rounds (made even: each order equally often)."""
    theta: str | None = None
    """A torch-saved θ to start every round from (default θ̃_0)."""
    label: str = "θ̃_0"


class Side:
    """One revision's worker process."""

    def __init__(self, label: str, path: Path | None, setup: Setup) -> None:
        self.label = label
        env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONHASHSEED="0")
        if path is not None:  # the commit's package alone: a folder on the caller's path that
            # holds this tree's ``fedhpg/__init__.py`` would make the worker import this tree
            env["PYTHONPATH"] = str(path)
        command = [sys.executable, str(WORKER), "--algo", setup.algo, "--agents",
                   str(setup.agents)]  # fmt: skip
        if setup.theta:
            command += ["--theta", setup.theta]
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True, env=env, cwd=tempfile.gettempdir())  # fmt: skip
        self.ready = self._answer()
        package = Path(str(self.ready.get("package", "")))
        if path is not None and "package" in self.ready and path not in package.parents:
            self.close()
            raise SystemExit(f"engine_ab: the {label} worker imported {package}, not the "
                             f"commit's package under {path}")  # fmt: skip

    def _answer(self) -> dict[str, Any]:
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line:
            code = self.process.wait()
            raise SystemExit(f"engine_ab: the {self.label} worker exited ({code}) before answering")
        return dict(json.loads(line))

    def round(self, index: int) -> dict[str, Any]:
        assert self.process.stdin is not None
        self.process.stdin.write(f"{index}\n")
        self.process.stdin.flush()
        return self._answer()

    def close(self) -> None:
        if self.process.stdin is not None:
            self.process.stdin.close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()


@dataclass(frozen=True)
class Comparison:
    setup: Setup
    ratio: float
    """Median over pairs of this tree's env steps per second / the commit's."""
    this_steps_per_s: float
    that_steps_per_s: float
    steps_per_round: tuple[float, float]
    that_group: str
    this_group: str
    sample_ns: tuple[float, float]
    """CPU ns a step spent sampling, this tree's and the commit's (0: not reported)."""
    gradient_ns: tuple[float, float]
    """CPU ns a step for the rest of the update (estimator, gradients, steps)."""


def compare(setup: Setup) -> Comparison:
    """The paired comparison (module docstring)."""
    rounds = setup.rounds + setup.rounds % 2
    sides = {"this": Side("this tree's", None, setup),
             "that": Side(f"{setup.against}'s", checkout(setup.against), setup)}  # fmt: skip
    rates: dict[str, list[float]] = {"this": [], "that": []}
    steps: dict[str, list[int]] = {"this": [], "that": []}
    phases: dict[str, list[tuple[float, float]]] = {"this": [], "that": []}
    try:
        for r in range(rounds + 1):  # round 0 compiles or loads kernels, and is dropped
            for name in ("this", "that") if r % 2 else ("that", "this"):
                answer = sides[name].round(r + 1)
                if r:
                    rates[name].append(answer["steps"] / answer["seconds"])
                    steps[name].append(int(answer["steps"]))
                    phases[name].append(
                        (
                            answer.get("engine_sample_s", 0.0) / answer["steps"],
                            answer.get("engine_gradient_s", 0.0) / answer["steps"],
                        )
                    )
            log.info("%s %s, %d agents: round %d/%d", setup.algo, setup.label, setup.agents,
                     r, rounds)  # fmt: skip
    finally:
        for side in sides.values():
            side.close()
    pairs = [a / b for a, b in zip(rates["this"], rates["that"], strict=True)]

    def ns(name: str, phase: int) -> float:
        return 1e9 * statistics.median(p[phase] for p in phases[name])

    return Comparison(
        setup=replace(setup, rounds=rounds),
        ratio=statistics.median(pairs),
        this_steps_per_s=statistics.median(rates["this"]),
        that_steps_per_s=statistics.median(rates["that"]),
        steps_per_round=(statistics.median(steps["this"]), statistics.median(steps["that"])),
        this_group=str(sides["this"].ready["group"]),
        that_group=str(sides["that"].ready["group"]),
        sample_ns=(ns("this", 0), ns("that", 0)),
        gradient_ns=(ns("this", 1), ns("that", 1)),
    )


def report(c: Comparison) -> str:
    s = c.setup
    return (
        f"{s.algo} at {s.label}, {s.agents} CartPole agents in one group, {s.rounds} interleaved "
        f"rounds: this tree ({c.this_group}) {c.this_steps_per_s / 1e6:.3f} M env steps/s "
        f"against {s.against} ({c.that_group}) {c.that_steps_per_s / 1e6:.3f} M; paired ratio "
        f"{c.ratio:.2f} ({c.steps_per_round[0]:,.0f} and {c.steps_per_round[1]:,.0f} steps a round)"
        f"\n  CPU a step: sampling {c.sample_ns[0]:.0f} ns against {c.sample_ns[1]:.0f}, "
        f"the rest of the update {c.gradient_ns[0]:.0f} ns against {c.gradient_ns[1]:.0f}"
    )


def save(comparisons: list[Comparison], path: Path = RESULTS) -> None:
    """Add ``comparisons`` to the results file (one entry per algorithm, K and θ)."""
    kept = json.loads(path.read_text()) if path.exists() else {}
    for c in comparisons:
        kept[f"{c.setup.algo}-{c.setup.agents}-{c.setup.label}"] = asdict(c)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(kept, indent=1, ensure_ascii=False) + "\n")


def load(path: Path = RESULTS) -> list[Comparison]:
    """The stored comparisons."""
    if not path.exists():
        return []
    found = []
    for entry in json.loads(path.read_text()).values():
        found.append(
            Comparison(
                **{
                    **entry,
                    "setup": Setup(**entry["setup"]),
                    "steps_per_round": tuple(entry["steps_per_round"]),
                    "sample_ns": tuple(entry["sample_ns"]),
                    "gradient_ns": tuple(entry["gradient_ns"]),
                }
            )
        )
    return found


NAMES = {"fedhpg": "FedHPG", "fedhpgvr": "FedHPGVR"}
THETAS = {
    "θ̃_0": "θ̃₀",
    "balancing": "a policy that balances for the 500-step horizon",
}
"""How the table names each starting θ (``--theta``'s label)."""


def _order(c: Comparison) -> tuple[int, int, bool, str]:
    return (list(NAMES).index(c.setup.algo), -c.setup.agents, c.setup.label != "θ̃_0",
            c.setup.label)  # fmt: skip


def _command(s: Setup) -> str:
    """The command line that repeats a comparison (its rounds as run: made even)."""
    default = Setup()
    words = ["python -m benchmarks.engine_ab"]
    if s.against != default.against:
        words.append(f"--against {s.against}")
    if s.algo != default.algo:
        words.append(f"--algo {s.algo}")
    if s.agents != default.agents:
        words.append(f"--agents {s.agents}")
    if s.label != default.label:
        words.append(f"--theta {s.label}")
    if s.rounds != default.rounds:
        words.append(f"--rounds {s.rounds}")
    return f"`{' '.join(words)}`"


def _rate(steps_per_s: float) -> str:
    millions = steps_per_s / 1e6
    return f"{millions:.2f}" if millions >= 0.1 else f"{millions:.2g}"


def _ratio(ratio: float) -> str:
    return f"{ratio:.2f}" if ratio < 10 else f"{ratio:.1f}"


def table(comparisons: list[Comparison], against: str = BASELINE) -> str:
    """Every stored comparison against ``against``: FedHPG before FedHPGVR, more agents first,
    θ̃₀ before another θ."""
    lines = [
        f"| command | algorithm, agents, θ | this tree (M steps/s) | {against} (M steps/s) "
        f"| paired ratio | CPU a step, sampling / the rest (ns), this tree against {against} |",
        "|---|---|---|---|---|---|",
    ]
    for c in sorted((c for c in comparisons if c.setup.against == against), key=_order):
        s = c.setup
        agents = f"{s.agents:,}" + (" (a lone agent)" if s.agents == 1 else "")
        cpu = f"{c.sample_ns[0]:.0f} / {c.gradient_ns[0]:.0f}"
        if c.sample_ns[1] == 0.0 and c.gradient_ns[1] == 0.0:
            cpu += f" ({against}'s {c.that_group} does not report the split)"
        else:
            cpu += f" against {c.sample_ns[1]:.0f} / {c.gradient_ns[1]:.0f}"
        lines.append(
            f"| {_command(s)} | {NAMES[s.algo]}, {agents}, {THETAS.get(s.label, s.label)} "
            f"| {_rate(c.this_steps_per_s)} | {_rate(c.that_steps_per_s)} "
            f"| **{_ratio(c.ratio)}** | {cpu} |"
        )
    return "\n".join(lines)


def summary(comparisons: list[Comparison], against: str = BASELINE) -> str:
    """Each algorithm's paired ratios by the number of agents (a range over the θ measured),
    against which of the commit's groups, and where this tree is the slower side."""
    chosen = sorted((c for c in comparisons if c.setup.against == against), key=_order)
    if not chosen:
        return "No comparison stored."
    parts, slower = [], []
    for algo, name in NAMES.items():
        runs = [c for c in chosen if c.setup.algo == algo]
        if not runs:
            continue
        by_agents = []
        for agents in sorted({c.setup.agents for c in runs}, reverse=True):
            ratios = [c.ratio for c in runs if c.setup.agents == agents]
            low, high = _ratio(min(ratios)), _ratio(max(ratios))
            by_agents.append(f"{low if low == high else f'{low}–{high}'} at {agents:,}")
            if float(high) < 1.0:
                slower.append(f"{name} at {agents:,}")
        groups = " and ".join(sorted({c.that_group for c in runs}))
        parts.append(f"{name} {', '.join(by_agents)} agents (against its {groups})")
    text = f"Paired ratios, this tree over {against}: {'; '.join(parts)}."
    if slower:
        text += f" This tree is the slower side for {' and '.join(slower)} agents."
    return text


def tables(comparisons: list[Comparison]) -> list[results_file.Table]:
    return [results_file.table_from_markdown(table(comparisons), summary(comparisons))]


def _balancing_theta(agents: int) -> str:
    """The balancing policy of the 16-16 MLP, saved where the workers can load it."""
    import torch

    from benchmarks.scale_device import balancing_theta
    from fedhpg.common.runtime.cli import compose

    run = compose(["env=cartpole", "agents=population", f"agents.num_agents={agents}",
                   "policy.hidden=[16,16]"])  # fmt: skip
    path = Path(tempfile.gettempdir()) / "fedhpg-engine-ab" / "balancing.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(balancing_theta(run), path)
    return str(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--against", default=BASELINE, help="the commit to compare with")
    parser.add_argument("--algo", default="fedhpg", choices=["fedhpg", "fedhpgvr"])
    parser.add_argument("--agents", type=int, default=500, help="agents in the group")
    parser.add_argument("--rounds", type=int, default=10, help="interleaved rounds (≥ 1)")
    parser.add_argument(
        "--theta",
        help="start every round from this θ (torch-saved .pt), or 'balancing': a policy that "
        "keeps the pole up for the whole horizon (benchmarks.scale_device.balancing_theta)",
    )
    parser.add_argument("--results", type=Path, default=RESULTS, help="JSON to add the result to")
    parser.add_argument(
        "--tables-only",
        action="store_true",
        help="only the result table from the stored comparisons, stamped with their measurement",
    )
    args = parser.parse_args()
    if args.tables_only:
        print(table(load()))
        results_file.rerender("engine_ab", tables(load()))
        return
    if args.rounds < 1 or args.agents < 1:
        parser.error("--rounds and --agents must be at least 1")
    label = "θ̃_0"
    if args.theta == "balancing":
        args.theta, label = _balancing_theta(args.agents), "balancing"
    elif args.theta:
        if not Path(args.theta).is_file():
            parser.error(f"--theta {args.theta}: no such file")
        label = Path(args.theta).stem
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    setup = Setup(
        against=args.against,
        algo=args.algo,
        agents=args.agents,
        rounds=args.rounds,
        theta=args.theta,
        label=label,
    )
    comparison = compare(setup)
    print(report(comparison))
    save([comparison], args.results)
    if args.results == RESULTS:
        # the section's command: each row of its table names the arguments it ran with
        results_file.refresh("engine_ab", tables(load()), "python -m benchmarks.engine_ab")


if __name__ == "__main__":
    main()
