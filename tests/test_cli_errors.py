"""Every bad input through the real entry points: exit status 2, exactly one line on stderr,
no traceback, and nothing left behind in the working directory (not even Hydra's
``outputs/<date>/<time>/``).

Each case runs in its own process and working directory. A few go through the console
scripts as subprocesses; the rest are forked from this process (already holding torch and
Hydra's imports, as ``fedhpg-run`` forks its children) and call the same installed entry
function with the same argv: ~0.2 s a case instead of ~1.7 s of imports.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fedhpg.common.configuration.config import to_dict
from fedhpg.common.runtime.cli import compose
from tests.procs import BIN, QUIET

RUN_DIR = "old-run"  # a run directory's config.json, made before the cases start
AS_SUBPROCESS = {"unknown-family", "sweep-bad-point", "server-unknown-family", "agent-typo"}
CASES: dict[str, tuple[str, list[str], str]] = {
    # id: (script, arguments, what the one line must say)
    "unknown-family": (
        "fedhpg-run",
        ["env.family=foo"],
        "env.family: unknown environment family 'foo'; known: acrobot",
    ),
    "bad-option": (
        "fedhpg-run",
        ["+env.options.bogus=1"],
        "env.options: bad options for env family 'gridworld'",
    ),
    "wrong-typed-option": ("fedhpg-run", ["+env.options.size=abc"], "env.options:"),
    "option-of-another-family": (
        "fedhpg-run",
        ["env=cartpole", "+env.options.size=7"],
        "env.options:",
    ),
    "fedpgbr-other-strategy": (
        "fedhpg-run",
        ["algo=fedpgbr", "strategy=median"],
        "strategy: algo=fedpgbr sends what only strategy=fedpgbr aggregates",
    ),
    "fedpgbr-strategy-other-algo": (
        "fedhpg-run",
        ["strategy=fedpgbr"],
        "strategy: fedpgbr aggregates gradients: it runs with an algorithm that sends them "
        "(algo=fedpgbr), not algo=fedhpg, which sends parameters",
    ),
    "host-beyond-the-protocol": (  # built 70,000 variants, then a traceback, before
        "fedhpg-agent",
        ["agents=population", "agents.num_agents=70000", "agent.first=0", "agent.count=70000"],
        "agent.count: got 70000, more than the 65536 agents one host may serve",
    ),
    "hosts-beyond-the-protocol": (
        "fedhpg-run",
        ["agents=population", "agents.num_agents=70000", "agents.per_host=70000"],
        "agents.per_host: got 70000, more than the 65536 agents one host may serve",
    ),
    "unknown-top-key": ("fedhpg-run", ["+foo=1"], "foo: not a fedhpg key"),
    "typo-added-with-plus": (
        "fedhpg-run",
        ["+rouds=3"],
        "rouds: not a fedhpg key; did you mean rounds?",
    ),
    "typo": ("fedhpg-run", ["rouds=3"], "rouds: not a fedhpg key; did you mean rounds?"),
    "nested-typo": (
        "fedhpg-run",
        ["+algo.stepsize=0.1"],
        "algo.stepsize: not a fedhpg key; did you mean algo.step_size?",
    ),
    "bad-value": (
        "fedhpg-run",
        ["agents.budget.batch_size=[0]"],
        "agents.budget.batch_size[0]: got 0",
    ),
    "unknown-group-option": ("fedhpg-run", ["algo=nope"], "algo: no such option 'nope'"),
    "plan-without-estimates": (
        "fedhpg-run",
        ["agents.plan=theorem1"],
        "agents.plan: theorem1 plans from Theorem 1's estimated constants: set "
        "algo.bound_estimates=true",
    ),
    "plan-of-fedhpgvr": (
        "fedhpg-run",
        ["algo=fedhpgvr", "agents.plan=theorem1"],
        "agents.plan: theorem1 plans Algorithm 1's batch_size and local_iters (fedhpg), not "
        "'fedhpgvr''s: Theorem 1 does not hold for it",
    ),
    "plan-every-zero": (
        "fedhpg-run",
        ["agents.plan_every=0"],
        "agents.plan_every: got 0, must be an integer >= 1",
    ),
    "plan-unknown": ("fedhpg-run", ["agents.plan=best"], "agents.plan: got 'best', allowed:"),
    "fedpgbr-buffered": (
        "fedhpg-run",
        ["algo=fedpgbr", "server.round_policy=buffered"],
        "server.round_policy: got 'buffered'; strategy=fedpgbr aggregates every agent's update "
        "at one θ̃ each round",
    ),
    "plan-buffered": (
        "fedhpg-run",
        ["agents.plan=theorem1", "algo.bound_estimates=true", "server.round_policy=buffered"],
        "agents.plan: theorem1 plans synchronous rounds; server.round_policy=buffered has none",
    ),
    "bad-port": ("fedhpg-run", ["server.port=70000"], "server.port: got 70000, must be <= 65535"),
    "host-not-here": (
        "fedhpg-run",
        ["server.host=192.0.2.1"],  # TEST-NET-1: no interface of this machine has it
        "server.host: cannot listen on 192.0.2.1: Cannot assign requested address",
    ),
    "out-dir-holds-a-run": (
        "fedhpg-run",
        [f"server.out_dir={RUN_DIR}"],
        f"server.out_dir: {RUN_DIR} holds a run already: continue it with resume=true",
    ),
    "out-dir-is-a-file": (
        "fedhpg-run",
        [f"server.out_dir={RUN_DIR}/config.json"],
        "is a file, not a directory",
    ),
    "bind-all": ("fedhpg-run", ["server.bind_all=true"], "server.bind_all:"),
    "unknown-flag": ("fedhpg-run", ["--bogus"], "--bogus: not an option"),
    "sweep-bad-point": (
        "fedhpg-run",
        ["-m", "seed=0,1", "algo.step_size=1,-1"],
        "sweep point 2/4 (seed=0 algo.step_size=-1): algo.step_size: got -1.0",
    ),
    "sweep-unknown-family": (
        "fedhpg-run",
        ["-m", "env.family=gridworld,foo"],
        "sweep point 2/2 (env.family=foo): env.family: unknown",
    ),
    "sweep-typo": (
        "fedhpg-run",
        ["--multirun", "+rouds=3,4"],
        "sweep point 1/2 (+rouds=3): rouds: not a fedhpg key",
    ),
    "sweep-resume": (
        "fedhpg-run",
        ["-m", f"resume={RUN_DIR}"],
        "resume: resume one run directory at a time",
    ),
    "resume-missing": (
        "fedhpg-run",
        ["resume=no-such-run"],
        "resume: no-such-run: no such directory",
    ),
    "resume-fixed-key": (
        "fedhpg-run",
        [f"resume={RUN_DIR}", "algo.step_size=0.1"],
        "algo.step_size: the run has 0.25, this invocation 0.1",
    ),
    "resume-fixed-group": (
        "fedhpg-run",
        [f"resume={RUN_DIR}", "strategy=median"],
        "strategy.name: the run has 'mean', this invocation 'median'",
    ),
    "server-unknown-family": (
        "fedhpg-server",
        ["env.family=foo"],
        "env.family: unknown environment family",
    ),
    "server-resume-no-dir": (
        "fedhpg-server",
        ["resume=true"],
        "resume: resume=true needs server.out_dir",
    ),
    "server-resume-fixed-key": (
        "fedhpg-server",
        ["resume=true", f"server.out_dir={RUN_DIR}", "seed=9"],
        "seed: the run has 0, this invocation 9",
    ),
    "agent-typo": ("fedhpg-agent", ["+rouds=3"], "rouds: not a fedhpg key; did you mean rounds?"),
    "agent-flag": ("fedhpg-agent", ["-x"], "-x: not an option"),
    "host-range-beyond-k": (
        "fedhpg-agent",
        ["agent.first=2", "agent.count=3"],
        "agent.first: the range 2..4 (agent.first, agent.count) goes beyond the last agent index 3",
    ),
    "host-count-zero": (
        "fedhpg-agent",
        ["agent.first=0", "agent.count=0"],
        "agent.count: got 0, must be an integer >= 1",
    ),
    "host-negative-first": ("fedhpg-agent", ["agent.first=-1"], "agent.first: got -1"),
    "per-host-zero": ("fedhpg-run", ["agents.per_host=0"], "agents.per_host: got 0"),
    "per-host-word": (
        "fedhpg-run",
        ["agents.per_host=many"],
        "agents.per_host: got 'many', must be 'auto' or an integer >= 1",
    ),
    # a setting its mode ignores: it ran the default mode and exited 0 before
    "trace-without-its-mode": (
        "fedhpg-run",
        ["strategy.participation.trace=bad.csv"],
        "strategy.participation.trace: got 'bad.csv', which mode 'all' does not use: add "
        "strategy.participation.mode=trace",
    ),
    "per-round-without-its-mode": (
        "fedhpg-run",
        ["strategy.participation.per_round=2"],
        "strategy.participation.per_round: got 2, which mode 'all' does not use: add "
        "strategy.participation.mode=uniform",
    ),
    # a gymnasium id or class where a family goes: it said "unexpected keyword argument 'seed'"
    "gym-id-as-family": (
        "fedhpg-run",
        ["env.family=MountainCar-v0"],
        "env.family: 'MountainCar-v0' is a gymnasium id, not an environment family: run it with "
        "env=gym env.id=MountainCar-v0",
    ),
    "gym-class-as-family": (
        "fedhpg-run",
        ["env.family=gymnasium.envs.classic_control:MountainCarEnv"],
        "env.family: gymnasium.envs.classic_control:MountainCarEnv is a gymnasium environment, "
        "not a family of variants: run it with env=gym",
    ),
    "gym-without-an-id": (
        "fedhpg-run",
        ["env=gym"],
        "env.id: env=gym needs a registered gymnasium id, e.g. env.id=MountainCar-v0",
    ),
    "gym-without-a-step-limit": (
        "fedhpg-run",
        ["env=gym", "env.id=CliffWalking-v1"],
        "env.horizon: CliffWalking-v1 has no step limit: set env.horizon=<steps>",
    ),
    "bounds-for-vr": (
        "fedhpg-run",
        ["algo=fedhpgvr", "algo.bound_estimates=true"],
        "algo.bound_estimates: Theorem 1's constants are estimated for Algorithm 1 (fedhpg) "
        "only, not 'fedhpgvr'",
    ),
    "buffered-hosts": (
        "fedhpg-run",
        ["server.round_policy=buffered", "agents.per_host=2"],
        "agents.per_host: got 2; server.round_policy=buffered takes one agent per process",
    ),
    "buffer-over-k": (
        "fedhpg-run",
        ["server.buffer_size=5"],
        "server.buffer_size: got 5, must be <= agents.num_agents=4",
    ),
    "negative-staleness": (
        "fedhpg-server",
        ["server.max_staleness=-1"],
        "server.max_staleness: got -1, must be an integer >= 0",
    ),
    # an integer no message of the wire carries: it started a federation that failed
    "rounds-beyond-64-bits": (
        "fedhpg-run",
        [f"rounds={10**30}"],
        f"rounds: got {10**30}, beyond the signed 64-bit integers a run's settings travel as",
    ),
    # a run directory that cannot be made: Hydra's traceback before
    "out-dir-under-a-file": (
        "fedhpg-run",
        [f"server.out_dir={RUN_DIR}/config.json/run"],
        f"server.out_dir: cannot create {RUN_DIR}/config.json/run: {RUN_DIR}/config.json is not "
        "a directory",
    ),
    "out-dir-in-proc": (
        "fedhpg-run",
        ["server.out_dir=/proc/fedhpg-run"],
        "server.out_dir: cannot create /proc/fedhpg-run: no directory can be made in /proc (",
    ),
    "out-dir-in-sys": (
        "fedhpg-run",
        ["server.out_dir=/sys/fedhpg/run"],
        "server.out_dir: cannot create /sys/fedhpg/run: no directory can be made in /sys (",
    ),
    # a key the user typed twice with different values: Hydra took the last one silently
    "key-given-twice": (
        "fedhpg-run",
        ["rounds=3", "rounds=4"],
        "rounds: given twice (rounds=3, rounds=4); give it once",
    ),
    "group-given-twice": (
        "fedhpg-run",
        ["env=cartpole", "env=acrobot"],
        "env: given twice (env=cartpole, env=acrobot); give it once",
    ),
    "key-given-twice-with-a-hydra-flag": (
        "fedhpg-run",
        ["--cfg", "job", "rounds=3", "rounds=4"],
        "rounds: given twice (rounds=3, rounds=4); give it once",
    ),
    "key-given-twice-in-a-sweep": (
        "fedhpg-run",
        ["-m", "seed=0,1", "+rounds=3", "rounds=4"],
        "rounds: given twice (+rounds=3, rounds=4); give it once",
    ),
    "resume-given-twice": (
        "fedhpg-run",
        [f"resume={RUN_DIR}", "resume=elsewhere"],
        f"resume: given twice (resume={RUN_DIR}, resume=elsewhere); give it once",
    ),
    "server-key-given-twice": (
        "fedhpg-server",
        ["seed=1", "seed=2"],
        "seed: given twice (seed=1, seed=2); give it once",
    ),
    "agent-key-given-twice": (
        "fedhpg-agent",
        ["agent.index=0", "agent.index=1"],
        "agent.index: given twice (agent.index=0, agent.index=1); give it once",
    ),
    "cluster-key-given-twice": (
        "fedhpg-cluster",
        ["cluster=local", "agents.num_agents=2", "agents.num_agents=3"],
        "agents.num_agents: given twice (agents.num_agents=2, agents.num_agents=3); give it once",
    ),
    "cluster-agent-index": (  # each agent job gets its own: a second one would be refused there
        "fedhpg-cluster",
        ["cluster=local", "agent.index=1"],
        "agent.index: fedhpg-cluster sets it for each agent job; leave it out",
    ),
    "plan-key-given-twice": (
        "fedhpg-plan",
        ["rounds=3", "rounds=4"],
        "rounds: given twice (rounds=3, rounds=4); give it once",
    ),
    # a section's name where a config group goes: an OmegaConf type message before
    "section-for-group": (
        "fedhpg-run",
        ["agent=demo4"],
        "agent: a section of settings (agent.KEY=VALUE), not a config group; did you mean "
        "agents=demo4?",
    ),
    "group-typo": (
        "fedhpg-run",
        ["experiments=fig1_batch_size"],
        "experiments: not a fedhpg key; did you mean experiment=fig1_batch_size?",
    ),
    # e.g. env=halfcheetah where fedhpg was installed without the envs extra (MuJoCo)
    "missing-simulator": (
        "fedhpg-run",
        ["env.family=fedhpg_toy_env_plugin:needs_a_missing_library"],
        "env.family: fedhpg_toy_env_plugin:needs_a_missing_library cannot be built here: "
        "FooSim is not installed",
    ),
}


def _listing(root: Path) -> set[str]:
    return {str(path.relative_to(root)) for path in root.rglob("*")}


def _forked(script: str, args: list[str], cwd: Path) -> tuple[int, str]:
    """Run the console script's entry function in a forked child, in ``cwd``."""
    (entry,) = importlib.metadata.entry_points(group="console_scripts", name=script)
    main = entry.load()
    err_path = cwd.parent / f"{cwd.name}.stderr"
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 70
        try:
            os.chdir(cwd)
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115
            sys.stderr = open(err_path, "w")  # noqa: SIM115
            sys.argv = [str(BIN / script), *args]
            os.environ.update(QUIET)
            try:
                main()
                code = 0
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else 1
            sys.stderr.flush()
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status), err_path.read_text()


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[int, str, set, set]]:
    """Every case, each in its own fresh working directory; the subprocesses start at once."""
    base = tmp_path_factory.mktemp("cli-errors")
    config = json.dumps(to_dict(compose(["algo.step_size=0.25"])))
    prepared = {}
    for name in CASES:
        cwd = base / name
        (cwd / RUN_DIR).mkdir(parents=True)
        (cwd / RUN_DIR / "config.json").write_text(config)
        (cwd / RUN_DIR / "metrics.jsonl").write_text("")  # a run's first file
        prepared[name] = (cwd, _listing(cwd))
    started = {
        name: subprocess.Popen(
            [str(BIN / CASES[name][0]), *CASES[name][1]],
            cwd=prepared[name][0],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **QUIET},
        )
        for name in AS_SUBPROCESS
    }
    results = {}
    try:
        for name, (script, args, _) in CASES.items():
            cwd, before = prepared[name]
            if name not in AS_SUBPROCESS:
                returncode, stderr = _forked(script, args, cwd)
                results[name] = (returncode, stderr, before, _listing(cwd))
        for name, process in started.items():
            _, stderr = process.communicate(timeout=120)
            cwd, before = prepared[name]
            results[name] = (process.returncode, stderr, before, _listing(cwd))
    finally:
        for process in started.values():
            if process.poll() is None:
                process.kill()
                process.wait()
    return results


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_input_is_one_line_exit_2_and_leaves_nothing(case: str, outcomes: dict) -> None:
    returncode, stderr, before, after = outcomes[case]
    expected = CASES[case][2]
    assert returncode == 2, stderr
    assert "Traceback" not in stderr
    assert stderr.count("\n") == 1 and stderr.endswith("\n"), stderr
    assert stderr.startswith("error: ") and expected in stderr, stderr
    assert after == before, f"left behind: {sorted(after - before)}"
