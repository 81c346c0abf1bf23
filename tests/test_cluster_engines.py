"""``fedhpg-cluster`` on a real SLURM and on a real Ray cluster, each of two nodes.

``cluster/slurm.sh`` starts slurmctld, slurmdbd (with its MariaDB) and munged, and one slurmd per
node; ``cluster/ray.sh`` a Ray head and a worker node. Each node is a network namespace of its
own with its own host name, so the server and the agent hosts really run on different "hosts"
and talk over the namespaces' links; every node sees this filesystem, as a cluster's nodes see a
shared one. ``fedhpg-cluster`` runs on the login node (the controller's or the head's namespace).
For each engine: a federation of two agent hosts ends with the θ̃ of ``fedhpg-run`` on loopback
with the same config, bit for bit, its jobs spread over both nodes; agent jobs killed mid-run in
every way the engine allows are restarted and the run still ends with that θ̃; Ctrl-C leaves no
job and no process.

Runs with ``make test-cluster`` (FEDHPG_CLUSTER_TESTS=1): the scripts install what they need
(Debian's SLURM, munge and MariaDB packages; the ``ray`` extra) and are skipped with their
reason where no cluster can run (not root, no network namespaces). Every ``fedhpg-cluster`` runs
under ``reaper.py``; the clusters' namespaces are searched for any process of a federation left
behind; the scripts stop what they started, by pid, when the module ends.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch
from procs import BIN, child_pids, sigint_ignored, wait_until

from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api

ROOT = Path(__file__).parents[1]
REAPER = Path(__file__).parent / "reaper.py"
SCRIPTS = {"slurm": ROOT / "cluster" / "slurm.sh", "ray": ROOT / "cluster" / "ray.sh"}
TIMEOUT_S = 300
ROUNDS = 40
RUN = [
    f"rounds={ROUNDS}", "seed=7", "agents.num_agents=4", "agents.per_host=2",
    "agents.budget.batch_size=[4]", "agents.budget.local_iters=[2]", "agents.speeds=[1]",
    "agents.step_delays_s=[0.005]", "eval.every=10", "eval.episodes=2", "server.tensorboard=false",
]  # fmt: skip
"""Two agent hosts of two agents; the step delay makes a round last ~0.3 s, so that crashes
land mid-run (a round waits for a crashed host to rejoin)."""
HOSTS = ("agent.first=0", "agent.first=2")
FEDERATION_WORDS = ("fedhpg-server", "fedhpg-agent", "submitit.core._submit", "ray::fedhpg")
"""What the processes of a federation's jobs have in their command lines (Ray names a worker
after the task it runs)."""

pytestmark = [
    pytest.mark.skipif(
        os.environ.get("FEDHPG_CLUSTER_TESTS") != "1",
        reason="real clusters are tested by make test-cluster (FEDHPG_CLUSTER_TESTS=1)",
    ),
    pytest.mark.timeout(1200),
]


@dataclass
class Cluster:
    """A running cluster: its clients run in ``login``, its jobs in ``nodes``."""

    kind: str
    login: str
    nodes: list[str]
    env: dict[str, str] = field(default_factory=dict)

    def client(self, *args: str) -> list[str]:
        return ["nsenter", f"--net=/run/netns/{self.login}", *args]

    def ask(self, *args: str) -> str:
        result = subprocess.run(
            self.client(*args), env={**os.environ, **self.env},
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert result.returncode == 0, f"{' '.join(args)}: {result.stderr[-2000:]}"
        return result.stdout

    def processes(self, *words: str) -> dict[int, str]:
        """Processes in the cluster's namespaces whose command line holds all ``words``."""
        found = {}
        for namespace in {self.login, *self.nodes}:
            listed = subprocess.run(
                ["ip", "netns", "pids", namespace], capture_output=True, text=True, timeout=10
            )
            for pid in map(int, listed.stdout.split()):
                line = _cmdline(pid)
                if line and all(w in line for w in words):
                    found[pid] = line
        return found

    def federation_left(self) -> dict[int, str]:
        return {
            pid: line for pid, line in self.processes().items()
            if any(word in line for word in FEDERATION_WORDS)
        }  # fmt: skip

    def busy(self) -> list[str]:
        """Jobs the engine still runs or queues: SLURM's queue; Ray's resources in use."""
        if self.kind == "slurm":
            return self.ask("squeue", "-h", "-o", "%i %T").split()
        probe = (
            "import json, ray; ray.init(logging_level='ERROR', log_to_driver=False); "
            "print(json.dumps([ray.cluster_resources(), ray.available_resources()]))"
        )
        total, free = json.loads(self.ask(str(BIN / "python"), "-c", probe).splitlines()[-1])
        return [f"{name}: {free.get(name, 0)} of {amount} free" for name, amount in total.items()
                if name in ("CPU", "GPU", "memory") and free.get(name, 0) < amount]  # fmt: skip


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
    except (OSError, UnicodeDecodeError):
        return ""


@pytest.fixture(scope="module", params=["slurm", "ray"])
def cluster(request: pytest.FixtureRequest) -> Iterator[Cluster]:
    script = SCRIPTS[request.param]
    result = subprocess.run(
        ["bash", str(script), "start", "2"], capture_output=True, text=True, timeout=1200
    )
    if result.returncode == 3:
        pytest.skip(result.stderr.strip().splitlines()[-1])
    assert result.returncode == 0, result.stderr
    values = dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)
    env = {k: values[k] for k in ("SLURM_CONF", "RAY_ADDRESS") if k in values}
    started = [int(p) for p in values.get("STARTED", "").split(",") if p]
    try:
        yield Cluster(request.param, values["NETNS"], values["NODES"].split(","), env)
    finally:
        if started:
            subprocess.run(["bash", str(script), "stop"], timeout=300, check=True)
            alive = [pid for pid in started if Path(f"/proc/{pid}").exists()]
            assert not alive, f"the {request.param} daemons this module started still run: {alive}"


@functools.cache
def _loopback_theta(out: Path) -> torch.Tensor:
    """θ̃ of ``fedhpg-run`` on loopback with ``RUN``: what every placement must end with."""
    run_dir = out / "loopback"
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), *RUN, f"server.out_dir={run_dir}",
         f"hydra.run.dir={out / 'hydra'}"],
        capture_output=True, text=True, timeout=TIMEOUT_S,
        env={**os.environ, "FEDHPG_LOG_LEVEL": "WARNING"},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    return _theta(run_dir)


@pytest.fixture(scope="module")
def loopback_theta(tmp_path_factory: pytest.TempPathFactory) -> torch.Tensor:
    return _loopback_theta(tmp_path_factory.getbasetemp() / "reference")


def _theta(run_dir: Path) -> torch.Tensor:
    checkpoint = latest_valid_checkpoint(run_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == ROUNDS, run_dir
    return checkpoint.theta


@dataclass
class Placed:
    """A running ``fedhpg-cluster`` (under the reaper), its run directory and its log."""

    process: subprocess.Popen
    run_dir: Path
    log: Path

    def driver(self) -> int:
        """fedhpg-cluster's own pid (the reaper's child: nsenter executes it)."""
        assert wait_until(lambda: bool(child_pids(self.process.pid)), 30)
        return child_pids(self.process.pid)[0]

    def rounds(self) -> int:
        metrics = self.run_dir / "metrics.jsonl"
        return len(metrics.read_text().splitlines()) if metrics.exists() else 0

    def port(self) -> int:
        assert wait_until(lambda: (self.run_dir / "endpoint.json").exists(), TIMEOUT_S)
        return int(json.loads((self.run_dir / "endpoint.json").read_text())["port"])

    def finish(self) -> tuple[int, str]:
        try:
            self.process.wait(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.end()
            pytest.fail(f"timed out: {self.log.read_text()[-3000:]}")
        text = self.log.read_text()
        assert "left behind" not in text, text[-3000:]
        return self.process.returncode, text

    def end(self) -> None:
        """SIGTERM to the driver (it then stops its jobs), SIGKILL to all if it lingers."""
        for sig, grace_s in ((signal.SIGTERM, 90.0), (signal.SIGKILL, 5.0)):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, sig)
            if wait_until(lambda: self.process.poll() is not None, grace_s):
                return


def _place(cluster: Cluster, tmp_path: Path, *extra: str) -> Placed:
    """``fedhpg-cluster`` with ``RUN``, the keys of ``extra`` in place of RUN's own (a key
    typed twice is refused)."""
    run_dir, log = tmp_path / "run", tmp_path / "fedhpg-cluster.log"
    replaced = {override.split("=", 1)[0] for override in extra}
    run = [override for override in RUN if override.split("=", 1)[0] not in replaced]
    command = cluster.client(
        str(BIN / "fedhpg-cluster"), f"cluster={cluster.kind}", f"server.out_dir={run_dir}",
        *run, *extra,
    )  # fmt: skip
    with log.open("w") as output:
        process = subprocess.Popen(
            [sys.executable, str(REAPER), *command], cwd=tmp_path, stdout=output, stderr=output,
            env={**os.environ, **cluster.env, "FEDHPG_LOG_LEVEL": "INFO"}, start_new_session=True,
        )  # fmt: skip
    return Placed(process, run_dir, log)


def _job_ids(log: str) -> list[str]:
    """The jobs fedhpg-cluster says it submitted, in order (the server's first)."""
    server = re.findall(r"submitted the server as job (\S+) ", log)
    agents = re.findall(r"submitted \d+ agent jobs: (.+)", log)
    restarts = re.findall(r"resubmitted as job (\S+) ", log)
    return [*server, *(j.strip() for line in agents for j in line.split(",")), *restarts]


def _slurm_jobs(cluster: Cluster, ids: list[str]) -> dict[str, tuple[str, str]]:
    """{job id: (state, node)} of ended jobs, from the accounting database (sacct), which
    slurmctld updates a moment after a job ends."""
    found: dict[str, tuple[str, str]] = {}

    def ended() -> bool:
        out = cluster.ask(
            "sacct", "-X", "-P", "-n", "-o", "JobID,State,NodeList", "-j", ",".join(ids)
        )
        rows = [line.split("|") for line in out.splitlines() if line]
        found.clear()
        found.update({job: (state, node) for job, state, node in rows})
        return set(found) >= set(ids) and not any(
            state.split()[0] in ("PENDING", "RUNNING", "COMPLETING") for state, _ in found.values()
        )

    assert wait_until(ended, 30, interval_s=0.5), f"sacct: {found}"
    return {job: found[job] for job in ids}


def _unit_hosts(run_dir: Path, kind: str) -> dict[str, str]:
    """{unit: host name it ran on} from each job's log ('running <command> (on <host>)')."""
    hosts = {}
    folder = run_dir / ("ray" if kind == "ray" else "submitit")
    for log in folder.glob("*/*_log.err"):
        for line in log.read_text().splitlines():
            match = re.search(r"running (fedhpg-\S+) .* \(on (\S+)\)$", line)
            if match:
                host = re.search(r"agent\.first=\d+", line)
                hosts[f"{match[1]} {host[0] if host else ''}".strip()] = match[2]
    return hosts


def _no_job_and_no_process(cluster: Cluster) -> None:
    busy = cluster.busy()
    assert not busy, f"{cluster.kind} still runs jobs: {busy}"
    assert wait_until(lambda: not cluster.federation_left(), 15), cluster.federation_left()


def test_a_federation_on_two_nodes_ends_with_the_theta_of_fedhpg_run(
    cluster: Cluster, tmp_path: Path, loopback_theta: torch.Tensor
) -> None:
    started = time.monotonic()
    placed = _place(cluster, tmp_path)
    status, log = placed.finish()
    assert status == 0, log[-3000:]
    print(f"fedhpg-cluster cluster={cluster.kind}: {time.monotonic() - started:.1f} s")
    assert torch.equal(_theta(placed.run_dir), loopback_theta)
    jobs = _job_ids(log)
    assert len(jobs) == 3, log[-3000:]  # the server and an array of two agent hosts
    hosts = _unit_hosts(placed.run_dir, cluster.kind)
    assert set(hosts) == {"fedhpg-server", *(f"fedhpg-agent {h}" for h in HOSTS)}, hosts
    assert set(hosts.values()) == set(cluster.nodes), f"not spread over both nodes: {hosts}"
    if cluster.kind == "slurm":
        accounted = _slurm_jobs(cluster, jobs)
        assert {state for state, _ in accounted.values()} == {"COMPLETED"}, accounted
        assert {node for _, node in accounted.values()} == set(cluster.nodes), accounted
    _no_job_and_no_process(cluster)


def _command_of(cluster: Cluster, host: str, port: int, exclude: set[int]) -> int:
    """The pid of agent host ``host``'s running command (not one of ``exclude``)."""
    found: list[int] = []

    def running() -> bool:
        pids = set(cluster.processes("bin/fedhpg-agent", f"{host} ", f"server.port={port}"))
        found[:] = sorted(pids - exclude)
        return bool(found)

    assert wait_until(running, TIMEOUT_S), f"{host}'s command did not (re)start"
    return found[0]


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _environ(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode().split("=", 1) for item in raw if b"=" in item)


def test_killed_agent_jobs_are_restarted_and_the_run_ends_with_the_same_theta(
    cluster: Cluster, tmp_path: Path, loopback_theta: torch.Tensor
) -> None:
    """Host 0's command is killed (kill -9), then host 1's job: on SLURM the array task is
    cancelled (scancel), on Ray its task's worker process is killed (kill -9); then, on SLURM,
    host 0's job process (kill -9). Each comes back as a new job, rejoins at the open round and
    redoes the lost work, so the run ends with the θ̃ of the undisturbed run."""
    placed = _place(cluster, tmp_path)
    killed: set[int] = set()
    try:
        assert wait_until(lambda: placed.rounds() >= 2, TIMEOUT_S), "no round completed"
        port = placed.port()

        def crash(host: str, how: str) -> None:
            command = _command_of(cluster, host, port, killed)
            killed.add(command)
            if how == "command":
                os.kill(command, signal.SIGKILL)
            elif how == "job process":  # the submitit process or Ray worker running the unit
                os.kill(_parent(command), signal.SIGKILL)
            else:  # scancel of its array task
                env = _environ(command)
                cluster.ask("scancel", f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}")
            at = placed.rounds()
            restarted = _command_of(cluster, host, port, killed)
            assert wait_until(lambda: placed.rounds() >= at + 2, TIMEOUT_S), "no rejoin"
            assert placed.rounds() < ROUNDS, f"the run ended before the next crash ({restarted})"

        crash(HOSTS[0], "command")
        if cluster.kind == "slurm":
            crash(HOSTS[1], "scancel")
            crash(HOSTS[0], "job process")
        else:
            crash(HOSTS[1], "job process")
    except BaseException:
        placed.end()
        raise
    status, log = placed.finish()
    assert status == 0, log[-3000:]
    assert torch.equal(_theta(placed.run_dir), loopback_theta)
    restarts = [line for line in log.splitlines() if "resubmitted as job" in line]
    assert len(restarts) == len(killed), log[-3000:]
    assert "agent.first=0 agent.count=2 exited with status -9; resubmitted" in restarts[0]
    assert "agent.first=2 agent.count=2" in restarts[1], restarts
    if cluster.kind == "slurm":
        assert "agent.first=0 agent.count=2 failed: it ended before its command did" in restarts[2]
        states = {state.split()[0] for state, _ in _slurm_jobs(cluster, _job_ids(log)).values()}
        assert states == {"COMPLETED", "CANCELLED", "FAILED"}, states
    else:
        assert "failed: it ended before its command did (The worker died" in restarts[1]
    _no_job_and_no_process(cluster)


def test_ctrl_c_leaves_no_job_and_no_process(cluster: Cluster, tmp_path: Path) -> None:
    """fedhpg-cluster starts with SIGINT ignored, as a shell's background job does (and as a
    test runner started in the background passes on), and must still stop on it."""
    with sigint_ignored():  # inherited by the driver at exec
        placed = _place(cluster, tmp_path, "rounds=1000000", "eval.every=1000000")
    try:
        assert wait_until(lambda: placed.rounds() >= 1, TIMEOUT_S), "no round completed"
        assert cluster.busy(), "no job running"
        os.kill(placed.driver(), signal.SIGINT)  # what Ctrl-C on its terminal sends it
    except BaseException:
        placed.end()
        raise
    status, log = placed.finish()
    assert status == 130, log[-3000:]
    assert "interrupted: cancelling the federation's jobs" in log
    _no_job_and_no_process(cluster)
    if cluster.kind == "slurm":  # each job's command was stopped and the job completed
        states = {state for state, _ in _slurm_jobs(cluster, _job_ids(log)).values()}
        assert states <= {"COMPLETED", "CANCELLED by 0"}, states


def test_a_request_the_cluster_cannot_meet_is_one_line_and_leaves_nothing(
    cluster: Cluster, tmp_path: Path
) -> None:
    """A GPU per agent host on clusters without GPUs: SLURM's sbatch refuses the agent array
    (the server job, already accepted, is cancelled); Ray would leave the tasks pending, so
    fedhpg-cluster refuses before submitting anything. One line, exit 1, no run directory."""
    placed = _place(cluster, tmp_path, "cluster.gpus_per_host=1")
    status, log = placed.finish()
    assert status == 1, log[-3000:]
    expected = {
        "slurm": "error: cannot submit the agent jobs: sbatch: error: Invalid generic resource "
        "(gres) specification (the server job is cancelled)",
        "ray": "error: the Ray cluster has 0 GPU, the run needs 2 at once (cluster.gpus_per_host)",
    }
    assert log.strip().splitlines()[-1] == expected[cluster.kind], log[-3000:]
    assert not placed.run_dir.exists()
    _no_job_and_no_process(cluster)


SWEEP = [
    "rounds=2", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "eval.every=2", "eval.episodes=2", "server.tensorboard=false",
]  # fmt: skip


def test_a_sweep_through_hydras_slurm_launcher_runs_each_point_as_a_job(
    cluster: Cluster, tmp_path: Path
) -> None:
    """``fedhpg-run -m seed=1,2 hydra/launcher=submitit_slurm``: each point a SLURM job (a whole
    federation on its node), each ending with its seed's θ̃ (the same run in this process)."""
    if cluster.kind != "slurm":
        pytest.skip("Hydra's submitit launcher places sweep points on SLURM, not on Ray")
    sweep, log = tmp_path / "sweep", tmp_path / "sweep.log"
    command = cluster.client(
        str(BIN / "fedhpg-run"), "-m", "seed=1,2", "hydra/launcher=submitit_slurm",
        f"hydra.sweep.dir={sweep}", *SWEEP,
    )  # fmt: skip
    with log.open("w") as output:
        result = subprocess.run(
            [sys.executable, str(REAPER), *command], cwd=tmp_path, stdout=output, stderr=output,
            env={**os.environ, **cluster.env}, timeout=TIMEOUT_S,
        )  # fmt: skip
    text = log.read_text()
    assert result.returncode == 0 and "left behind" not in text, text[-3000:]
    nodes = set()
    for job, seed in ((0, 1), (1, 2)):
        checkpoint = latest_valid_checkpoint(sweep / str(job) / "checkpoints")
        assert checkpoint is not None and checkpoint.round == 2
        assert torch.equal(checkpoint.theta, api.run(overrides=[*SWEEP, f"seed={seed}"]).theta)
        logs = list((sweep / ".submitit").glob(f"*_{job}/*_log.out"))
        assert len(logs) == 1, logs
        job_id = logs[0].parent.name
        state, node = _slurm_jobs(cluster, [job_id])[job_id]
        assert state == "COMPLETED", state
        nodes.add(node)
    assert nodes == set(cluster.nodes), f"both points on one node: {nodes}"
    _no_job_and_no_process(cluster)
