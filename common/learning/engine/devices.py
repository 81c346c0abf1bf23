"""Which torch device the engine may use here: ``algo.device`` checked before anything runs.

CUDA cannot be used in a process forked after its parent initialised it, and ``fedhpg-run``
forks the server and every agent: a process about to fork asks a fresh interpreter
(:func:`cuda_devices_in_a_fresh_process`), never CUDA itself.
"""

from __future__ import annotations

import functools
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError

if TYPE_CHECKING:
    import torch


class DeviceUnavailable(ConfigError):
    """``algo.device`` names a device this machine's torch cannot use."""

    def __init__(self, problem: str) -> None:
        super().__init__("algo.device", problem)


def cuda_devices_here() -> int:
    """How many CUDA devices torch sees, asked in this process: it initialises CUDA here, and
    CUDA then fails in every process forked from this one afterwards."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


_PROBE = "import torch; print(torch.cuda.device_count() if torch.cuda.is_available() else 0)"


@functools.cache
def cuda_devices_in_a_fresh_process() -> int | str:
    """How many CUDA devices torch sees, asked in a fresh interpreter, so that this process
    (``fedhpg-run``'s, which forks the agents next) leaves CUDA untouched; or why the
    question got no answer."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=300
        )
    except (OSError, subprocess.SubprocessError) as error:
        return str(error)
    answer = done.stdout.strip()
    if done.returncode != 0 or not answer.isdigit():
        lines = (done.stderr.strip() or f"exit status {done.returncode}").splitlines()
        return lines[-1]
    return int(answer)


def device_problem(device: str, *, before_fork: bool = False) -> str | None:
    """Why this machine cannot run the engine on ``algo.device`` (None: it can).

    ``before_fork``: asked by a process that forks the agents afterwards, which must not
    touch CUDA itself (torch and CUDA refuse CUDA in a process forked after it)."""
    if not device.startswith("cuda"):
        return None
    import torch

    if before_fork and torch.cuda.is_initialized():
        return (
            f"{device!r}: this process has already used CUDA, so the agents it forks "
            "could not: start the federation from a process that has not"
        )
    if not before_fork and getattr(torch.cuda, "_is_in_bad_fork", lambda: False)():
        return (
            f"{device!r}: this process was forked from one that had used CUDA, which "
            "CUDA does not allow: start it from a process that has not"
        )
    count = cuda_devices_in_a_fresh_process() if before_fork else cuda_devices_here()
    if isinstance(count, str):
        return f"{device!r}: could not ask torch for this machine's CUDA devices: {count}"
    if count == 0:
        return f"{device!r}: torch sees no CUDA device on this machine"
    index = int(device.partition(":")[2] or 0)
    if index >= count:
        return f"{device!r}: this machine has {count} CUDA device(s)"
    return None


def check_device_before_fork(run: RunConfig) -> None:
    """Raise :class:`DeviceUnavailable` (a :class:`ConfigError`) where a process about to
    fork the run's agents (the launcher, ``api.run(distributed=True)``) finds that they could
    not use ``algo.device``."""
    problem = device_problem(run.algo.device, before_fork=True)
    if problem is not None:
        raise DeviceUnavailable(problem)


def check_device(device: str) -> None:
    """Raise :class:`DeviceUnavailable` where this process cannot use ``device``."""
    problem = device_problem(device)
    if problem is not None:
        raise DeviceUnavailable(problem)


@contextmanager
def deterministic_off_cpu(device: torch.device) -> Iterator[None]:
    """Torch's deterministic algorithms (warn_only) inside, where ``device`` is not the CPU:
    a GPU's scatter-adds (the backward of a gather, as the tabular policy's) add with
    atomics, in an order that changes from run to run and with the company. The caller's
    setting is restored after (a notebook is not left changed); on the CPU, or where the caller
    has already turned them on, nothing changes."""
    import torch

    if device.type == "cpu" or torch.are_deterministic_algorithms_enabled():
        yield
        return
    import torch.utils.deterministic

    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    # deterministic mode would also fill every new tensor (NaN), a pass over memory per
    # allocation: the engine writes what it allocates before reading it
    fill = torch.utils.deterministic.fill_uninitialized_memory  # type: ignore[attr-defined]
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(False, warn_only=warn_only)
        torch.utils.deterministic.fill_uninitialized_memory = fill  # type: ignore[attr-defined]
