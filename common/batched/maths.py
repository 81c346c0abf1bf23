"""Where the numpy engine's policy maths run: numpy on this CPU (the default, bit-identical
across placements), or torch on a device (``algo.engine=torch``, ``algo.device``).

The engine keeps the environments, the random streams, the coefficients and the ascent
steps in numpy on the CPU either way; a :class:`PolicyMaths` does the three things whose cost
grows with the policy: the per-agent layers built from θ rows, each step's forward and
action draw, and the score-function gradient of ended batches.
"""

from __future__ import annotations

import functools
import subprocess
import sys
from typing import Any, Protocol

import numpy as np

from fedhpg.common.batched import mlp
from fedhpg.common.config import ConfigError, RunConfig


class PolicyMaths(Protocol):
    """Per-agent MLP maths on some device; ``layers`` values are the device's arrays."""

    def unflatten(self, shape: mlp.MLPShape, theta: np.ndarray) -> Any:
        """Per-agent layers from θ rows [A, d] (copies)."""

    def select(self, layers: Any, rows: np.ndarray) -> Any:
        """The layers of agents ``rows`` (copies)."""

    def assign(self, layers: Any, rows: np.ndarray, fresh: Any) -> None:
        """Overwrite agents ``rows`` of ``layers`` with ``fresh`` (from :meth:`unflatten`)."""

    def act(self, layers: Any, obs: np.ndarray, uniforms: np.ndarray | None) -> np.ndarray:
        """Actions [A·n] of obs [A, n, in]: categorical draws by ``uniforms`` [A·n], or the
        greedy ones where ``uniforms`` is None."""

    def score_gradient(self, shape: mlp.MLPShape, layers: Any, chunks: mlp.Chunks) -> np.ndarray:
        """Σ_rows coef · ∇_θ log π(a|s) per agent, [A, d] float32, as in :mod:`.mlp`."""


class NumpyMaths:
    """:mod:`fedhpg.common.batched.mlp` as it is: an agent's numbers do not depend on its
    company, so placement does not change θ."""

    def unflatten(self, shape: mlp.MLPShape, theta: np.ndarray) -> mlp.Layers:
        return mlp.unflatten(shape, theta)

    def select(self, layers: mlp.Layers, rows: np.ndarray) -> mlp.Layers:
        return mlp.select(layers, rows)

    def assign(self, layers: mlp.Layers, rows: np.ndarray, fresh: mlp.Layers) -> None:
        for (weight, bias), (new_w, new_b) in zip(layers, fresh, strict=True):
            weight[rows], bias[rows] = new_w, new_b

    def act(self, layers: mlp.Layers, obs: np.ndarray, uniforms: np.ndarray | None) -> np.ndarray:
        logit = mlp.logits(layers, obs)
        logit = logit.reshape(-1, logit.shape[-1])
        if uniforms is None:
            return np.asarray(logit.argmax(axis=-1), dtype=np.int64)
        return mlp.draw_actions(logit, uniforms)

    def score_gradient(
        self, shape: mlp.MLPShape, layers: mlp.Layers, chunks: mlp.Chunks
    ) -> np.ndarray:
        return mlp.score_gradient(shape, layers, chunks)


NUMPY = NumpyMaths()


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


def device_problem(engine: str, device: str, *, before_fork: bool = False) -> str | None:
    """Why this machine cannot run ``algo.engine`` on ``algo.device`` (None: it can).

    ``before_fork``: asked by a process that forks the agents afterwards, which must not
    touch CUDA itself (torch and CUDA refuse CUDA in a process forked after it)."""
    if engine != "torch" or not device.startswith("cuda"):
        return None
    import torch

    if before_fork and torch.cuda.is_initialized():
        return (f"{device!r}: this process has already used CUDA, so the agents it forks "
                "could not: start the federation from a process that has not")  # fmt: skip
    if not before_fork and getattr(torch.cuda, "_is_in_bad_fork", lambda: False)():
        return (f"{device!r}: this process was forked from one that had used CUDA, which "
                "CUDA does not allow: start it from a process that has not")  # fmt: skip
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
    problem = device_problem(run.algo.engine, run.algo.device, before_fork=True)
    if problem is not None:
        raise DeviceUnavailable(problem)


def maths_for(engine: str, device: str) -> PolicyMaths:
    """The maths of ``algo.engine`` on ``algo.device``."""
    if engine != "torch":
        return NUMPY
    problem = device_problem(engine, device)
    if problem is not None:
        raise DeviceUnavailable(problem)
    from fedhpg.common.batched.torch_maths import TorchMaths

    return TorchMaths(device)
