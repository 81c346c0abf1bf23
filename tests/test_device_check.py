"""Whether this machine can run the engine on ``algo.device=cuda…``, asked the
way CUDA allows: the process that forks the agents (``fedhpg-run``'s launcher,
``api.run(distributed=True)``) never asks CUDA itself, since CUDA refuses every process forked
after its parent used it; a fresh interpreter asks instead (common/learning/engine/devices.py)."""

from __future__ import annotations

import pytest
import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.learning.engine import devices as maths
from fedhpg.common.learning.engine.devices import DeviceUnavailable, check_device
from fedhpg.server.commands import api
from fedhpg.server.commands.api import resolve_config


def _run(device: str):
    return resolve_config(
        overrides=["env=cartpole", "agents=population", "agents.num_agents=6",
                   "algo.engine=torch", f"algo.device={device}"]
    )  # fmt: skip


def _cuda_forbidden(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any question to CUDA in this process fails the test."""

    def touched(*_args: object) -> int:
        raise AssertionError("this process asked CUDA: agents it forks could not use it")

    for name in ("is_available", "device_count", "current_device", "init"):
        monkeypatch.setattr(torch.cuda, name, touched)
    monkeypatch.setattr(torch._C, "_cuda_getDeviceCount", touched, raising=False)


def test_the_launcher_checks_the_device_without_touching_cuda(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # CUDA refuses a process forked after its parent asked it anything (torch poisons the
    # fork), and fedhpg-run forks the agents after its checks: a fresh interpreter asks
    from fedhpg.server.commands.launcher import check_launch

    maths.cuda_devices_in_a_fresh_process.cache_clear()
    _cuda_forbidden(monkeypatch)
    wanted = (r"^algo.device: 'cuda:99': (torch sees no CUDA device on this machine"
              r"|this machine has \d+ CUDA device\(s\))$")  # fmt: skip
    with pytest.raises(ConfigError, match=wanted):
        check_launch(_run("cuda:99"))
    with pytest.raises(ConfigError, match=wanted):  # the API forks its agents the same way
        api.run(_run("cuda:99"), distributed=True)


def test_the_device_count_decides_the_device(monkeypatch: pytest.MonkeyPatch) -> None:
    for count, device, problem in [
        (2, "cuda:1", None),
        (2, "cuda", None),
        (2, "cuda:2", "'cuda:2': this machine has 2 CUDA device(s)"),
        (0, "cuda", "'cuda': torch sees no CUDA device on this machine"),
        ("ImportError: libcuda.so.1", "cuda",
         "'cuda': could not ask torch for this machine's CUDA devices: ImportError: libcuda.so.1"),
    ]:  # fmt: skip
        monkeypatch.setattr(maths, "cuda_devices_in_a_fresh_process", lambda c=count: c)
        monkeypatch.setattr(maths, "cuda_devices_here", lambda c=count: c)
        for before_fork in (True, False):
            assert maths.device_problem(device, before_fork=before_fork) == problem
    assert maths.device_problem("cpu", before_fork=True) is None


def test_cuda_used_before_a_fork_is_one_line_on_both_sides(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(maths, "cuda_devices_in_a_fresh_process", lambda: 1)
    monkeypatch.setattr(maths, "cuda_devices_here", lambda: 1)
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    assert maths.device_problem("cuda", before_fork=True) == (
        "'cuda': this process has already used CUDA, so the agents it forks could not: "
        "start the federation from a process that has not"
    )
    monkeypatch.setattr(torch.cuda, "_is_in_bad_fork", lambda: True, raising=False)
    with pytest.raises(DeviceUnavailable, match=r"^algo.device: 'cuda': this process was forked"):
        check_device("cuda")
