"""``make bench-device`` (benchmarks/scale_device.py), rehearsed on the CPU: the rows at θ̃₀
and at the balancing policy, the reference beside them, the memory plan, the placement check,
and the reference module itself (every copy alive at every step)."""

from __future__ import annotations

import importlib
import inspect
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from benchmarks import device_reference, scale_device

ROOT = Path(__file__).parents[1]


def test_the_rehearsal_reports_engine_reference_memory_and_placement(tmp_path) -> None:
    """In a process of its own, as ``make bench-device`` runs it: a peak of resident memory is
    measured against what the process held before, which a test worker's earlier tests set."""
    out = tmp_path / "scale_device.json"
    command = [sys.executable, "-m", "benchmarks.scale_device", "--device", "cpu", "--agents",
               "12,24", "--repeats", "1", "--compare-up-to", "12", "--families",
               "cartpole,pendulum", "--out", str(out)]  # fmt: skip
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "scale_device_report.json").read_text())
    rows = result["parts"]["scale_device"]["rows"]
    assert [(r["agents"], r["policy"]) for r in rows] == [
        (12, "initial"), (12, "balancing"), (24, "initial"), (24, "balancing")
    ]  # fmt: skip
    balancing = [r for r in rows if r["policy"] == "balancing"]
    assert all(r["env_steps"] == r["agents"] * 16 * 500 for r in balancing), "every pole stays up"
    assert all(r["env_steps"] < r["agents"] * 16 * 100 for r in rows if r["policy"] == "initial")
    assert [r["compiled_steps_per_s"] is not None for r in rows] == [True, True, False, False]
    assert all(0 < r["device_peak_mib"] <= r["planned_peak_mib"] for r in balancing)
    reference = result["parts"]["scale_device"]["reference"]
    assert [r["agents"] for r in reference] == [12, 24]
    assert all(r["peak_mib"] is None for r in reference), "no CUDA device measured"
    placement = result["placement"]
    assert list(placement["families"]) == ["cartpole", "pendulum"]
    assert placement["same_theta_in_any_company"] and placement["same_theta_on_a_second_run"]
    printed = done.stdout
    assert "| 24 | balancing | 192,000 |" in printed and "same theta in any company: yes" in printed


def test_a_part_stopped_at_its_limit_is_reported_as_missing(tmp_path, capsys) -> None:
    """The report of parts one of which stopped before its engine rows (the reference alone
    written) and a federation that never ran: the rows it has, what is missing, exit 1."""
    part = tmp_path / "k12.json"
    scale_device.main(["--device", "cpu", "--only", "iteration", "--agents", "12",
                       "--repeats", "1", "--out", str(part)])  # fmt: skip
    stopped = tmp_path / "k24.json"
    record = json.loads(part.read_text())
    record["rows"] = []
    record["reference"] = [{**record["reference"][0], "agents": 24}]
    stopped.write_text(json.dumps(record))
    parts = [str(part), str(stopped), str(tmp_path / "none.json")]
    federation = [str(tmp_path / "no-run"), "100", "124", "0"]
    with pytest.raises(SystemExit) as stop:
        scale_device.main(["--report", *parts, "--out", str(tmp_path / "report.json"),
                           "--federation", *federation])  # fmt: skip
    assert stop.value.code == 1
    printed = capsys.readouterr().out
    assert "| 12 | balancing |" in printed and "no engine row" in printed
    assert "K = [24]" in printed and "placement check: not finished" in printed
    assert "0 of 3 rounds done, exit status 124" in printed
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["federation"]["rounds"] == [] and report["placement"] is None


def test_the_reference_counts_every_copy_at_every_step() -> None:
    got = device_reference.measure(3, 4, torch.device("cpu"), steps=8, gradient=True, repeats=1)
    assert got.steps_per_s == pytest.approx(3 * 4 * 8 / got.seconds)
    reference = device_reference.Reference(2, 3, torch.device("cpu"))
    before = [p.detach().clone() for p in reference.params]
    observations, actions, rewards, ended = reference.rollout(50)
    assert observations.shape == (50, 6, 4) and bool(ended.any())
    limit = device_reference.THETA_LIMIT
    assert float(observations[:, :, 2].abs().max()) <= limit, "reset once the pole fell"
    reference.update(observations, actions, rewards, ended)
    assert any(not torch.equal(a, b) for a, b in zip(before, reference.params, strict=True))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--device", "tpu"], "error: --device: got 'tpu', allowed: cpu, cuda, cuda:N"),
        (["--agents", "0"], "error: need --agents as positive integers (1000,16000) and "
         "--repeats >= 1"),
        (["--agents", "ten"], "error: need --agents as positive integers (1000,16000) and "
         "--repeats >= 1"),
    ],
)  # fmt: skip
def test_bad_arguments_are_one_line(args: list[str], message: str) -> None:
    with pytest.raises(SystemExit) as stop:
        scale_device.main(args)
    assert stop.value.code == message


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
@pytest.mark.parametrize("module", ["scale_device", "device_profile"])
def test_no_cuda_device_is_one_line(module: str) -> None:
    main = importlib.import_module(f"benchmarks.{module}").main
    with pytest.raises(SystemExit) as stop:
        main(["--device", "cuda:0"])
    assert stop.value.code == "error: --device: 'cuda:0': torch sees no CUDA device on this machine"


def test_the_profile_splits_a_round_into_sections_and_operators(tmp_path) -> None:
    """device_profile times each engine section of a real round (each > 0, together no more
    than the round), names torch's busiest operators, and leaves the engine as it was."""
    from benchmarks import device_profile
    from fedhpg.common.learning.engine.torch_backend import TorchBackend

    before = {
        name: inspect.getattr_static(TorchBackend, name)
        for name in device_profile.SECTIONS.values()
    }
    out = tmp_path / "profile.json"
    device_profile.main(["--device", "cpu", "--agents", "2", "--policies", "balancing",
                         "--out", str(out)])  # fmt: skip
    (entry,) = json.loads(out.read_text())["rounds"]
    assert entry["env_steps"] == 2 * scale_device.BATCH * 500  # every pole up to the horizon
    sections = entry["sections_s"]
    assert set(sections) == {*device_profile.SECTIONS, "the rest"}
    assert all(sections[name] > 0 for name in device_profile.SECTIONS)
    timed = sum(sections[name] for name in device_profile.SECTIONS)
    assert timed <= entry["sectioned_iteration_s"]  # sections inside the round, none twice
    operators = [op["operator"] for op in entry["top_operators"]]
    assert entry["operators_ranked_by"] == "cpu"
    assert "aten::bmm" in operators  # the policy's per-row matrix products
    after = {
        name: inspect.getattr_static(TorchBackend, name)
        for name in device_profile.SECTIONS.values()
    }
    assert after == before
