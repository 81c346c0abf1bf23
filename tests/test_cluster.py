"""Past one machine: Hydra sweeps through the joblib and submitit launchers, and a federation
placed through submitit (``fedhpg-cluster cluster=local``: submitit's LocalExecutor, the same
jobs, files and logs as on SLURM). The real SLURM and Ray are tests/test_cluster_engines.py's
(make test-cluster); here, in make test, SLURM's commands are stand-ins.

Real processes throughout: every command runs under ``reaper.py``, a child subreaper that
names (and kills) any process still alive after the command exits, so a job, a forked server
or an agent left behind fails the test. Every run is checked against the same seed run in this
process by ``api.run``: the θ̃ of the distributed run must be equal bit for bit."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from procs import BIN, child_pids, sigint_ignored, wait_until

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.runtime.cli import compose
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api
from fedhpg.server.commands.cluster.main import check_placement

REAPER = Path(__file__).parent / "reaper.py"
TIMEOUT_S = 120
TINY = [
    "rounds=2", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "eval.every=2", "eval.episodes=2", "server.tensorboard=false",
]  # fmt: skip


def tiny(*overrides: str) -> list[str]:
    """TINY with ``overrides`` in place of its own values: a command line gives a key once."""
    keys = {o.split("=", 1)[0] for o in overrides}
    return [*(o for o in TINY if o.split("=", 1)[0] not in keys), *overrides]


def _run(args: list[str], cwd: Path, *, env: dict[str, str] | None = None) -> subprocess.Popen:
    """The command under the reaper, in a process group of its own (submitit's local jobs stay
    in it), so that a failing test can end all of it."""
    return subprocess.Popen(
        [sys.executable, str(REAPER), *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "FEDHPG_LOG_LEVEL": "INFO", **(env or {})},
        start_new_session=True,
    )


def _end_group(process: subprocess.Popen) -> None:
    """SIGTERM to the whole group (fedhpg-cluster then stops its jobs), SIGKILL if it lingers."""
    for sig, grace_s in ((signal.SIGTERM, 15.0), (signal.SIGKILL, 5.0)):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, sig)
        if wait_until(lambda: process.poll() is not None, grace_s):
            return


def _finish(process: subprocess.Popen) -> tuple[int, str, str]:
    try:
        out, err = process.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        _end_group(process)
        out, err = process.communicate()
        pytest.fail(f"timed out: {err[-3000:]}")
    assert "left behind" not in err, err[-3000:]
    return process.returncode, out, err


def _theta(run_dir: Path) -> torch.Tensor:
    checkpoint = latest_valid_checkpoint(run_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 2, run_dir
    return checkpoint.theta


@functools.cache  # the sweeps check seeds 1 and 2 each
def _in_process(seed: int) -> torch.Tensor:
    return api.run(overrides=[*TINY, f"seed={seed}"]).theta


def _check_sweep(sweep: Path) -> None:
    """Two complete runs, one per seed, each the θ̃ of its seed; the seeds' θ̃ differ."""
    thetas = []
    for job, seed in ((0, 1), (1, 2)):
        run_dir = sweep / str(job)
        assert json.loads((run_dir / "config.json").read_text())["seed"] == seed
        assert len((run_dir / "metrics.jsonl").read_text().splitlines()) == 2
        assert json.loads((run_dir / "summary.json").read_text())["final_eval_round"] == 2
        thetas.append(_theta(run_dir))
        assert torch.equal(thetas[-1], _in_process(seed)), f"seed {seed}"
    assert not torch.equal(thetas[0], thetas[1])


def _ports(stderr: str) -> set[str]:
    return {line.rsplit(":", 1)[1].split(",")[0] for line in stderr.splitlines()
            if "server listening on tcp://" in line}  # fmt: skip


def test_the_driver_shows_each_round_and_ends_with_the_servers_final_table(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture
) -> None:
    """fedhpg-cluster follows the server job's metrics.jsonl in the shared run directory: a
    progress line per round as fedhpg-run shows them, whole lines only, then the final table
    the server prints, from summary.json."""
    import logging

    from fedhpg.server.commands.cluster.main import RoundProgress
    from fedhpg.server.serving import final_report

    run_dir = tmp_path / "run"
    result = api.run(overrides=TINY, out_dir=run_dir)
    run = compose(TINY)
    lines = (run_dir / "metrics.jsonl").read_bytes().splitlines(keepends=True)
    shared = tmp_path / "shared"
    shared.mkdir()
    rounds = RoundProgress(run, shared)
    with caplog.at_level(logging.INFO, logger="fedhpg.common.runtime.progress"):
        rounds.poll()  # the server has not written it yet
        (shared / "metrics.jsonl").write_bytes(lines[0] + lines[1][:40])  # round 2 half-written
        rounds.poll()
        with (shared / "metrics.jsonl").open("ab") as handle:
            handle.write(lines[1][40:])
        rounds.poll()
        rounds.close()
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("progress")]
    assert [s.split(" [")[0] for s in said] == ["progress 1/2 rounds", "progress 2/2 rounds"]
    assert "| eval success min" in said[1], said

    (shared / "summary.json").write_bytes((run_dir / "summary.json").read_bytes())
    capsys.readouterr()
    rounds.report()
    out = capsys.readouterr().out
    assert result.last_evaluation is not None
    table = final_report(run, result.last_evaluation, ["agent-0", "agent-1"], has_goal=True)
    assert "Unified policy after round 2 (2 greedy episodes per environment):" in out
    assert table in out and f"run directory: {shared.resolve()}" in out


def test_reaper_sees_a_process_left_behind(tmp_path: Path) -> None:
    process = _run(["sh", "-c", "sleep 30 & exit 0"], tmp_path)
    _, err = process.communicate(timeout=30)
    assert process.returncode == 99 and "left behind" in err and "sleep 30" in err


@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_a_two_seed_sweep_runs_both_seeds_side_by_side(tmp_path: Path, launcher: str) -> None:
    sweep = tmp_path / "sweep"
    started = time.monotonic()
    process = _run(
        [
            str(BIN / "fedhpg-run"), "-m", "seed=1,2", f"hydra/launcher={launcher}",
            f"hydra.sweep.dir={sweep}", *TINY,
            *(["hydra.launcher.n_jobs=2"] if launcher == "joblib" else []),
        ],
        tmp_path,
    )  # fmt: skip
    status, out, err = _finish(process)
    assert status == 0, err[-3000:]
    elapsed = time.monotonic() - started
    _check_sweep(sweep)
    if launcher == "joblib":  # the jobs' logs come here: two federations on two free ports
        assert len(_ports(err)) == 2, err[-3000:]
        assert out.count("run directory:") == 2
    else:  # each job's log is in submitit's folder; its own free port there
        logs = "".join(p.read_text() for p in (sweep / ".submitit").glob("*/*_log.err"))
        assert len(_ports(logs)) == 2 and logs.count("Job completed successfully") == 2, logs
    print(f"{launcher} sweep: {elapsed:.1f} s")


@pytest.mark.slow
def test_a_federation_placed_through_submitit_equals_the_same_run_here(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    started = time.monotonic()
    process = _run(
        [str(BIN / "fedhpg-cluster"), "cluster=local", f"server.out_dir={run_dir}", *TINY],
        tmp_path,
    )
    status, out, err = _finish(process)
    assert status == 0, err[-3000:]
    print(f"fedhpg-cluster cluster=local: {time.monotonic() - started:.1f} s")
    assert f"run directory: {run_dir}" in out
    assert "progress 2/2 rounds" in err and "Unified policy after round 2" in out, (out, err)
    assert torch.equal(_theta(run_dir), _in_process(0))
    endpoint = json.loads((run_dir / "endpoint.json").read_text())
    assert endpoint["host"] == "127.0.0.1" and endpoint["port"] > 0
    # one server job and an array of two agent jobs, each through its own submitit job
    logs = sorted((run_dir / "submitit").glob("*/*_0_log.err"))
    assert len(logs) == 3, logs
    texts = [p.read_text() for p in logs]
    assert sum("running fedhpg-server" in t for t in texts) == 1
    for k in (0, 1):
        line = f"agent.index={k} server.host=127.0.0.1 server.port={endpoint['port']}"
        assert sum(line in t for t in texts) == 1, texts
    assert all("Job completed successfully" in t for t in texts)


@pytest.mark.slow
def test_agent_hosts_placed_through_submitit_equal_the_same_run_here(tmp_path: Path) -> None:
    """With agents.per_host the job array holds the hosts: agents 0..1 and agent 2."""
    run_dir = tmp_path / "run"
    keys = tiny("agents.num_agents=3", "agents.per_host=2")
    process = _run(
        [str(BIN / "fedhpg-cluster"), "cluster=local", f"server.out_dir={run_dir}", *keys],
        tmp_path,
    )
    status, _, err = _finish(process)
    assert status == 0, err[-3000:]
    assert torch.equal(_theta(run_dir), api.run(overrides=[*keys, "seed=0"]).theta)
    texts = [p.read_text() for p in sorted((run_dir / "submitit").glob("*/*_0_log.err"))]
    assert len(texts) == 3, "one server job, two host jobs"
    for unit in ("agent.first=0 agent.count=2", "agent.first=2 agent.count=1"):
        assert sum(unit in t for t in texts) == 1, texts


def _agent_pid(index: int, port: int) -> int | None:
    """The pid of the fedhpg-agent command of agent ``index`` connected to ``port``."""
    wanted = ("fedhpg-agent", f"agent.index={index}", f"server.port={port}")
    for entry in Path("/proc").iterdir():
        try:
            words = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except (OSError, ValueError):
            continue
        program = any(w.endswith(f"/{wanted[0]}") for w in words[:2])  # python, the script
        if program and all(w in words for w in wanted[1:]):
            return int(entry.name)
    return None


def _rounds(run_dir: Path) -> int:
    metrics = run_dir / "metrics.jsonl"
    return len(metrics.read_text().splitlines()) if metrics.exists() else 0


@pytest.mark.slow
def test_a_crashed_agent_job_is_resubmitted_and_a_dead_server_ends_all(tmp_path: Path) -> None:
    """Agent 1's process is killed mid-run: its job is resubmitted and the run goes on. Then
    the server process is killed: one line naming its job, exit 1, and the agent jobs (which
    would wait for a server that will not come back) are stopped."""
    run_dir = tmp_path / "run"
    process = _run(
        [
            str(BIN / "fedhpg-cluster"), "cluster=local", f"server.out_dir={run_dir}",
            *tiny("rounds=1000000", "eval.every=1000000"),
        ],
        tmp_path,
        env={"FEDHPG_LOG_LEVEL": "WARNING"},
    )  # fmt: skip
    try:
        assert wait_until(lambda: _rounds(run_dir) > 0, TIMEOUT_S), "no round completed"
        port = json.loads((run_dir / "endpoint.json").read_text())["port"]
        agent = _agent_pid(1, port)
        assert agent is not None
        os.kill(agent, 9)
        killed_at = _rounds(run_dir)
        assert wait_until(lambda: _agent_pid(1, port) not in (None, agent), TIMEOUT_S)
        assert wait_until(lambda: _rounds(run_dir) > killed_at + 10, TIMEOUT_S), "no rejoin"
        os.kill(int((run_dir / ".lock").read_text()), 9)  # the server's pid
    except BaseException:
        _end_group(process)
        raise
    status, _, err = _finish(process)
    assert status == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 2, err
    assert "agent job of fedhpg-agent agent.index=1 exited with status -9; resubmitted" in lines[0]
    assert lines[1].startswith("error: the server job ") and "exited with status -9" in lines[1]
    assert "log: " in lines[1]
    assert len([d for d in (run_dir / "submitit").iterdir() if d.name.isdigit()]) == 4


@pytest.mark.slow
def test_ctrl_c_stops_the_jobs_of_a_driver_started_with_sigint_ignored(tmp_path: Path) -> None:
    """fedhpg-cluster started as a shell's background job is (SIGINT ignored, inherited at
    exec) still stops on SIGINT: it says so, ends every job (the reaper names any process left)
    and exits 130."""
    run_dir = tmp_path / "run"
    with sigint_ignored():
        process = _run(
            [
                str(BIN / "fedhpg-cluster"), "cluster=local", f"server.out_dir={run_dir}",
                *tiny("rounds=1000000", "eval.every=1000000"),
            ],
            tmp_path,
        )  # fmt: skip
    try:
        assert wait_until(lambda: _rounds(run_dir) > 0, TIMEOUT_S), "no round completed"
        assert wait_until(lambda: bool(child_pids(process.pid)), 30)
        os.kill(child_pids(process.pid)[0], signal.SIGINT)  # the reaper's child: fedhpg-cluster
    except BaseException:
        _end_group(process)
        raise
    status, _, err = _finish(process)
    assert status == 130, err[-3000:]
    assert "interrupted: cancelling the federation's jobs" in err
    assert "stopped jobs " in err


@pytest.mark.parametrize(
    ("args", "env", "expected"),
    [
        (["cluster.kind=pbs"], {}, "error: cluster.kind: got 'pbs', allowed: auto, slurm, local,"),
        (["cluster=pbs"], {}, "error: cluster: no such option 'pbs'; allowed: local, ray, slurm"),
        (["cluster.gpus_per_host=-1"], {}, "error: cluster.gpus_per_host: got -1, must be an"),
        ([], {"PYTHONPATH": "NO_SUBMITIT"}, "error: fedhpg-cluster needs submitit: pip install"),
    ],
)
def test_mistakes_are_one_line_and_submit_nothing(
    tmp_path: Path, args: list[str], env: dict[str, str], expected: str
) -> None:
    if env:  # a submitit that cannot be imported, as when it is not installed
        blocker = tmp_path / "blocker" / "submitit"
        blocker.mkdir(parents=True)
        (blocker / "__init__.py").write_text("raise ImportError('no submitit here')\n")
        env = {"PYTHONPATH": str(blocker.parent)}
    work = tmp_path / "work"
    work.mkdir()
    process = _run([str(BIN / "fedhpg-cluster"), *TINY, *args], work, env=env)
    status, _, err = _finish(process)
    assert status == 2, err
    assert err.strip().splitlines() == [err.strip()] and err.startswith(expected), err
    assert list(work.iterdir()) == [], "nothing created"


def test_an_array_that_cannot_hold_every_agent_at_once_is_refused(tmp_path: Path) -> None:
    """In this process (the entry point's one-line path is the one above): the check itself."""
    run = compose([*TINY, "cluster.array_parallelism=1"])
    with pytest.raises(ConfigError, match="got 1, below the 2 agent jobs: the server waits"):
        check_placement(run, [])
    run = compose([*TINY, "cluster.array_parallelism=2", f"server.out_dir={tmp_path / 'r'}"])
    assert check_placement(run, []) == (tmp_path / "r").resolve()
    assert not (tmp_path / "r").exists()


FAKE_SBATCH = """#!/bin/sh
# The first submission is accepted as job 42, the next refused, as sbatch refuses a bad one.
dir=$(dirname "$0")
n=$(ls "$dir"/sbatch-*.sh 2>/dev/null | wc -l)
cp "$1" "$dir/sbatch-$n.sh"
if [ "$n" = 0 ]; then echo "Submitted batch job 42"; exit 0; fi
echo "sbatch: error: Batch job submission failed: Invalid partition name specified" >&2
exit 1
"""


FAKE_SACCT = """#!/bin/sh
# Job 42 is pending until the stand-in scancel has cancelled it.
echo "JobID|State|NodeList"
if [ -f "$(dirname "$0")/scancel.log" ]; then echo "42|CANCELLED by 0|"; else echo "42|PENDING|"; fi
"""


def test_slurm_jobs_go_through_sbatch_and_a_refusal_cancels_the_server_job(
    tmp_path: Path,
) -> None:
    """Without a SLURM (make test): stand-in sbatch, scancel, srun and sacct on PATH (the only
    stand-ins in this file) take what submitit's real SLURM executor sends them. The server
    job's script asks for what cluster.* says, GPUs for the agent jobs alone; the agents are
    one array of two; when sbatch refuses the array, the accepted server job is cancelled, one
    line says why, exit 1, and the run directory that nothing ran in is gone once sacct reports
    the server job cancelled. tests/test_cluster_engines.py runs the same on a real SLURM (make
    test-cluster)."""
    bin_dir = tmp_path / "slurm-bin"
    bin_dir.mkdir()
    scripts = {
        "sbatch": FAKE_SBATCH,
        "scancel": '#!/bin/sh\necho "$@" >> "$(dirname "$0")/scancel.log"\n',
        "srun": "#!/bin/sh\nexit 0\n",
        "sacct": FAKE_SACCT,
    }
    for name, text in scripts.items():
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    run_dir = tmp_path / "run"
    process = _run(
        [
            str(BIN / "fedhpg-cluster"), "cluster=slurm", "cluster.partition=cpu",
            "cluster.time_min=7", "cluster.mem_gb=3", "cluster.cpus_per_task=2",
            "cluster.gpus_per_host=1", f"server.out_dir={run_dir}", *TINY,
        ],
        tmp_path,
        env={"PATH": f"{bin_dir}:{os.environ['PATH']}", "FEDHPG_LOG_LEVEL": "WARNING"},
    )  # fmt: skip
    status, _, err = _finish(process)
    assert status == 1, err
    assert err.strip().splitlines()[-1] == (
        "error: cannot submit the agent jobs: sbatch: error: Batch job submission failed: "
        "Invalid partition name specified (the server job is cancelled)"
    )
    server, agents = ((bin_dir / f"sbatch-{n}.sh").read_text() for n in (0, 1))
    for line in ("--partition=cpu", "--time=7", "--mem=3GB", "--cpus-per-task=2"):
        assert f"#SBATCH {line}\n" in server and f"#SBATCH {line}\n" in agents
    assert "#SBATCH --gres=gpu:1\n" in agents and "--gres" not in server
    assert "#SBATCH --job-name=fedhpg-server\n" in server
    assert "#SBATCH --job-name=fedhpg-agent\n" in agents and "#SBATCH --array=0-1%2\n" in agents
    assert "-m submitit.core._submit" in server
    assert (bin_dir / "scancel.log").read_text().split() == ["42"]
    assert not run_dir.exists()


RAY_BLOCKER = """import os
open(os.environ["RAY_MARKER"], "w").write("imported")
raise ImportError("ray is not to be imported here")
"""
IMPORT_ALL = """import importlib, pkgutil, sys
import fedhpg.agent, fedhpg.common, fedhpg.envs, fedhpg.server
names = [m.name for p in (fedhpg.agent, fedhpg.common, fedhpg.envs, fedhpg.server)
         for m in pkgutil.walk_packages(p.__path__, p.__name__ + ".")]
for name in names:
    if name != "fedhpg.server.commands.cluster.ray_engine":
        importlib.import_module(name)
print(len(names))
"""


@pytest.mark.slow
def test_ray_is_imported_by_cluster_ray_alone(tmp_path: Path) -> None:
    """A ``ray`` that records being imported (and fails): importing every module of the package
    but the Ray engine, and a whole ``fedhpg-cluster cluster=local`` run, jobs included, never
    touch it. (The import contract in pyproject.toml checks the same of the source.)"""
    blocker = tmp_path / "blocker" / "ray"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text(RAY_BLOCKER)
    marker = tmp_path / "ray-imported"
    env = {**os.environ, "PYTHONPATH": str(blocker.parent), "RAY_MARKER": str(marker)}
    result = subprocess.run(
        [sys.executable, "-c", IMPORT_ALL], env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert int(result.stdout) > 100 and not marker.exists()
    run_dir = tmp_path / "run"
    process = _run(
        [str(BIN / "fedhpg-cluster"), "cluster=local", f"server.out_dir={run_dir}", *TINY],
        tmp_path,
        env={"PYTHONPATH": str(blocker.parent), "RAY_MARKER": str(marker)},
    )
    status, _, err = _finish(process)
    assert status == 0, err[-3000:]
    assert not marker.exists()
    # cluster=ray does import it; without it, one line and nothing started
    work = tmp_path / "work"
    work.mkdir()
    process = _run(
        [str(BIN / "fedhpg-cluster"), "cluster=ray", *TINY],
        work,
        env={"PYTHONPATH": str(blocker.parent), "RAY_MARKER": str(marker)},
    )
    status, _, err = _finish(process)
    assert marker.exists()
    assert status == 2 and err == "error: fedhpg-cluster needs ray: pip install 'fedhpg[ray]'\n"
    assert list(work.iterdir()) == []


def test_only_fedhpg_cluster_lists_the_cluster_keys() -> None:
    from fedhpg.common.runtime.help import help_text

    own = help_text("fedhpg-cluster")
    assert own.startswith("usage: fedhpg-cluster [cluster=local|slurm|ray]")
    assert "cluster.kind=auto" in own and "cluster.array_parallelism=null" in own
    assert "cluster=     local, ray, slurm" in own
    for other in ("fedhpg-run", "fedhpg-server", "fedhpg-agent"):
        text = help_text(other)
        assert "cluster." not in text and "cluster=" not in text, other
        assert "server.endpoint_file=null" in text
