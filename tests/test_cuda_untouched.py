"""No process of a federation whose maths run on the CPU asks CUDA anything.

Where torch has CUDA, a process forked after its parent asked CUDA anything cannot use CUDA
("Cannot re-initialize CUDA in forked subprocess"), and ``fedhpg-run`` forks the server and the
agents: one question in the launcher and every child fails as soon as it asks one itself.
``tests/cuda_trace/sitecustomize.py`` records every call of torch's CUDA and accelerator
queries, in the launcher and in every process forked from it. A CPU build answers them, so
what would initialise CUDA on a GPU machine shows here.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TRACER = Path(__file__).parent / "cuda_trace"
FEDHPG_RUN = Path(sys.executable).parent / "fedhpg-run"


def _traced(args: list[str], where: Path) -> str:
    """Run ``args`` with the tracer loaded; what it recorded ('' if nothing)."""
    log = where / "cuda-questions.log"
    path = os.pathsep.join(p for p in (str(TRACER), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "FEDHPG_CUDA_TRACE": str(log), "PYTHONPATH": path}
    done = subprocess.run(args, env=env, cwd=where, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    return log.read_text(encoding="utf-8") if log.exists() else ""


def test_the_tracer_sees_a_cuda_question(tmp_path: Path) -> None:
    # what build_policy did before: fork_rng reaches for every CUDA device
    trace = _traced([sys.executable, "-c", "import torch\nwith torch.random.fork_rng(): pass"],
                    tmp_path)  # fmt: skip
    assert "torch.cuda.device_count" in trace and "fork_rng" in trace


TORCH_MATHS_ON_HOSTS = ["env=cartpole", "agents=population", "agents.num_agents=12",
                        "agents.per_host=4", "algo.engine=torch", "algo.device=cpu"]  # fmt: skip


@pytest.mark.parametrize(
    "overrides", [[], TORCH_MATHS_ON_HOSTS], ids=["demo", "torch-maths-on-cpu-hosts"]
)
def test_fedhpg_run_on_the_cpu_never_asks_cuda(tmp_path: Path, overrides: list[str]) -> None:
    trace = _traced([str(FEDHPG_RUN), "rounds=1", *overrides, f"hydra.run.dir={tmp_path / 'run'}"],
                    tmp_path)  # fmt: skip
    assert trace == "", f"a process of the run asked CUDA:\n{trace[:4000]}"


def test_a_distributed_api_run_never_asks_cuda(tmp_path: Path) -> None:
    code = (
        "from fedhpg.server.commands import api\napi.run(overrides=['rounds=1'], distributed=True)"
    )
    trace = _traced([sys.executable, "-c", code], tmp_path)
    assert trace == "", f"a process of the run asked CUDA:\n{trace[:4000]}"
