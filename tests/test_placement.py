"""Placement never changes the MDP: an agent host started with another seed either trains on
the server's MDP (the variant is the same, the server dictates the training seed) or is
refused at registration in one line (its variant differs). Real processes, loopback TCP."""

from __future__ import annotations

from pathlib import Path

import torch
from procs import free_port, processes, start

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint

TIMEOUT_S = 120
RUN = [
    "rounds=4", "agents.num_agents=2", "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    "eval.every=4", "eval.episodes=4",
]  # fmt: skip


def _federation(tmp_path: Path, server: list[str], agent_1: list[str]) -> tuple[int, str, Path]:
    out_dir = tmp_path / "run"
    wire = [f"server.port={free_port()}", f"server.out_dir={out_dir}"]
    with processes() as started:
        serving = start(started, "fedhpg-server", [*RUN, *server, *wire], cwd=tmp_path)
        start(started, "fedhpg-agent", [*RUN, *server, *wire, "agent.index=0"], cwd=tmp_path)
        stray = start(
            started, "fedhpg-agent", [*RUN, *agent_1, *wire, "agent.index=1"], cwd=tmp_path
        )
        _, stray_err = stray.communicate(timeout=TIMEOUT_S)
        if stray.returncode != 0:  # refused: the right host joins instead
            start(started, "fedhpg-agent", [*RUN, *server, *wire, "agent.index=1"], cwd=tmp_path)
        _, server_err = serving.communicate(timeout=TIMEOUT_S)
        assert serving.returncode == 0, server_err[-2000:]
    return stray.returncode, stray_err, out_dir


def _final_theta(out_dir: Path) -> torch.Tensor:
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 4
    return checkpoint.theta


def test_a_host_whose_seed_makes_another_variant_is_refused_in_one_line(tmp_path: Path) -> None:
    status, stderr, out_dir = _federation(tmp_path, ["seed=3"], ["seed=4"])
    assert status == 1
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    assert "variant_mismatch" in lines[0] and "seed and env.*" in lines[0]
    assert torch.equal(_final_theta(out_dir), run_in_process(compose([*RUN, "seed=3"])))


def test_a_host_with_another_seed_but_the_same_variant_trains_on_the_servers_run(
    tmp_path: Path,
) -> None:
    """env.seed pins the variants, so the stray host's own seed=4 builds the run's variant;
    the server dictates the seed of its training streams: θ̃ is the seed-3 run's."""
    status, stderr, out_dir = _federation(
        tmp_path, ["seed=3", "env.seed=3"], ["seed=4", "env.seed=3"]
    )
    assert status == 0, stderr[-2000:]
    expected = run_in_process(compose([*RUN, "seed=3", "env.seed=3"]))
    assert torch.equal(_final_theta(out_dir), expected)
    assert not torch.equal(expected, run_in_process(compose([*RUN, "seed=4", "env.seed=3"])))
