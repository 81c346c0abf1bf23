"""``make bench-device`` (benchmarks/scale_device.py), run on the CPU: the doubling of K, its
stops, the same-process comparisons and the placement check."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from benchmarks import scale_device


def _main(tmp_path: Path, *args: str) -> dict:
    out = tmp_path / "scale_device.json"
    scale_device.main(["--device", "cpu", "--out", str(out), *args])
    return json.loads(out.read_text())


def test_k_doubles_to_the_cap_with_ratios_and_the_placement_check(tmp_path, capsys) -> None:
    result = _main(tmp_path, "--start", "15", "--max-agents", "60", "--compare-up-to", "30")
    rows = result["rows"]
    assert [r["agents"] for r in rows] == [15, 30, 60]
    assert result["largest_agents"] == 60 and "--max-agents" in result["stopped"]
    assert all(r["env_steps"] >= 8 * r["agents"] and r["round_s"] > 0 for r in rows)
    assert [r["compiled_round_s"] is not None for r in rows] == [True, True, False]
    assert [r["compiled_round_s"] is not None for r in rows] == [True, True, False]
    assert all(r["device_peak_mib"] is None for r in rows), "no CUDA device measured"
    # on the CPU, torch's products keep an agent's θ independent of its company
    assert result["same_theta_in_any_company"] and result["same_theta_on_a_second_run"]
    printed = capsys.readouterr().out
    assert "largest K reached: 60" in printed and "| 30 |" in printed


def test_a_slow_round_stops_the_doubling(tmp_path) -> None:
    result = _main(tmp_path, "--start", "10", "--max-round-s", "0", "--compare-up-to", "0")
    assert [r["agents"] for r in result["rows"]] == [10]
    assert "> --max-round-s" in result["stopped"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--device", "tpu"], "error: --device: got 'tpu', allowed: cpu, cuda, cuda:N"),
        (["--device", "cudax"], "error: --device: got 'cudax', allowed: cpu, cuda, cuda:N"),
        (["--start", "0"], "error: need 1 <= --start <= --max-agents and --hidden >= 1"),
    ],
)
def test_bad_arguments_are_one_line(args, message) -> None:
    with pytest.raises(SystemExit) as stop:
        scale_device.main(args)
    assert stop.value.code == message


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_no_cuda_device_is_one_line() -> None:
    with pytest.raises(SystemExit) as stop:
        scale_device.main(["--device", "cuda:0"])
    assert stop.value.code == "error: --device: 'cuda:0': torch sees no CUDA device on this machine"
