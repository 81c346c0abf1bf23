"""Server crash and resume: kill -9 the server mid-run, corrupt its newest checkpoint, restart
it with resume=true; the agents register again by themselves and the run ends with exactly the
θ of an uninterrupted run, with the paper's plain averaging and with a server-side Adam whose
moments the checkpoint carries."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
import torch
from procs import free_port, processes, start, start_federation, wait_until

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import checkpoint_files, latest_valid_checkpoint

ROUNDS = 10


@pytest.mark.parametrize(
    "strategy",
    # a stateful strategy (Adam's moments) over a robust inner rule: the stateless mean's resume
    # is a subset of it, and fedhpg-run's resume test below runs the default strategy
    # (two agents: a median of two tolerates no attacker, which this test does not need)
    [["strategy=fedadam", "strategy.params.inner=median", "strategy.tolerance_check=warn"]],
    ids=["fedadam-median"],
)
def test_killed_server_resumes_to_the_same_theta(tmp_path: Path, strategy: list[str]) -> None:
    """Kill -9 the server mid-run, tear its newest checkpoint, resume: the final θ̃ is the
    uninterrupted in-process one, bit for bit, also with fedadam's moments in the checkpoint."""
    out_dir = tmp_path / "run"
    run_keys = [
        f"rounds={ROUNDS}", "seed=5", "agents.num_agents=2", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[2]", "agents.speeds=[1]", "agents.step_delays_s=[0.002]",
        "eval.every=5", "eval.episodes=5", *strategy,
    ]  # fmt: skip
    if "strategy=fedadam" in strategy:
        run_keys.append("strategy.params.step_size=0.05")
    wire = [f"server.port={free_port()}", f"server.out_dir={out_dir}"]
    metrics = out_dir / "metrics.jsonl"
    with processes() as started:
        server, agents = start_federation(started, [*run_keys, *wire], 2, cwd=tmp_path)
        assert wait_until(
            lambda: metrics.exists() and len(metrics.read_text().splitlines()) >= 4, 60
        )
        server.send_signal(signal.SIGKILL)
        server.wait(timeout=10)
        newest = checkpoint_files(out_dir / "checkpoints")[-1]
        newest.write_bytes(newest.read_bytes()[:-7])  # a torn write
        restarted = start(started, "fedhpg-server", [*run_keys, *wire, "resume=true"], cwd=tmp_path)
        _, stderr = restarted.communicate(timeout=120)
        assert restarted.returncode == 0, stderr[-2000:]
        for agent in agents:
            agent.wait(timeout=30)
    assert "skipping checkpoint" in stderr and "torn or corrupt file" in stderr
    assert "resuming" in stderr
    assert [a.returncode for a in agents] == [0, 0]
    records = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert [r["round"] for r in records] == list(range(1, ROUNDS + 1)), "none lost or doubled"
    steps = [r["trajectories_per_agent"] for r in records]
    assert steps == [12.0 * r for r in range(1, ROUNDS + 1)], "counters continue across the kill"
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == ROUNDS
    assert torch.equal(checkpoint.theta, run_in_process(compose(run_keys)))


# ~18 s: make test-long. fast cover: tests/test_resume.py::
# test_killed_server_resumes_to_the_same_theta (kill -9 mid-run, resume, θ̃ the uninterrupted
# one bit for bit), tests/test_cli_output.py::
# test_named_port_one_log_format_and_resume_from_the_run_directory (fedhpg-run resume=DIR from
# the run's config.json) and tests/test_launcher.py::test_children_die_with_a_killed_launcher
@pytest.mark.slow
def test_killed_launcher_resumes_with_fedhpg_run_resume_dir(tmp_path: Path) -> None:
    """``fedhpg-run resume=DIR``: the whole local federation is killed (its children die with
    it), then resumed from the run directory; the final θ̃ is the uninterrupted one."""
    out_dir = tmp_path / "run"
    run_keys = [
        f"rounds={ROUNDS}", "seed=8", "agents.num_agents=2", "agents.budget.batch_size=[6]",
        "agents.budget.local_iters=[2]", "agents.speeds=[1]", "agents.step_delays_s=[0.003]",
        "eval.every=5", "eval.episodes=5",
    ]  # fmt: skip
    metrics = out_dir / "metrics.jsonl"
    hydra_dir = f"hydra.run.dir={tmp_path / 'hydra'}"
    with processes() as started:
        first = start(
            started, "fedhpg-run", [*run_keys, f"server.out_dir={out_dir}", hydra_dir], cwd=tmp_path
        )
        assert wait_until(
            lambda: metrics.exists() and len(metrics.read_text().splitlines()) >= 3, 60
        )
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=10)
        resumed = start(
            started, "fedhpg-run", [*run_keys, f"resume={out_dir}", hydra_dir], cwd=tmp_path
        )
        stdout, stderr = resumed.communicate(timeout=120)
    assert resumed.returncode == 0, (stdout + stderr)[-2000:]
    assert "resuming" in stdout + stderr
    records = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert [r["round"] for r in records] == list(range(1, ROUNDS + 1))
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == ROUNDS
    assert torch.equal(checkpoint.theta, run_in_process(compose(run_keys)))


def test_resume_auto_starts_a_fresh_directory_and_resumes_one_that_holds_a_run(
    tmp_path: Path,
) -> None:
    """resume=auto (what a supervisor's restart needs: one command for both cases): a fresh
    start where server.out_dir holds no run, resume=true where it does, with the same checks
    (a changed fixed key is refused); continuing in Python gives the uninterrupted θ̃."""
    from fedhpg.common.configuration.config_error import ConfigError
    from fedhpg.server.commands import api

    keys = ["seed=4", "agents=homogeneous4", "agents.budget.batch_size=[4]", "eval.every=10"]
    out_dir = tmp_path / "run"
    auto = ["resume=auto", f"server.out_dir={out_dir}"]
    assert compose([*keys, *auto, "rounds=2"], resumable=True).resume is None
    api.run(overrides=[*keys, "rounds=2"], out_dir=out_dir)
    resumed = compose([*keys, *auto, "rounds=4"], resumable=True)
    assert (resumed.resume or "").lower() == "true" and resumed.rounds == 4
    with pytest.raises(ConfigError, match="seed"):
        compose([*keys, *auto, "rounds=4", "seed=5"], resumable=True)
    with pytest.raises(ConfigError, match=r"server\.out_dir"):
        compose([*keys, "resume=auto"], resumable=True)
    continued = api.run(overrides=[*keys, "rounds=4", "resume=auto"], out_dir=out_dir)
    assert [r["round"] for r in continued.records] == [1, 2, 3, 4]
    uninterrupted = api.run(overrides=[*keys, "rounds=4"])
    assert torch.equal(continued.theta, uninterrupted.theta)


@pytest.mark.parametrize("value", ["false", "False", "null", "none"])
def test_resume_false_means_no_resume(value: str) -> None:
    """Hydra reads resume=false as a boolean, which the str field made "False": a server then
    claimed and tried to resume a directory named False in its working directory."""
    assert compose([f"resume={value}"], resumable=True).resume is None
    assert compose([f"resume={value}"]).resume is None
