"""Where the numpy engine's policy maths run: numpy on this CPU (the default, bit-identical
across placements), or torch on a device (``algo.engine=torch``, ``algo.device``).

The engine keeps the environments, the random streams, the coefficients and the ascent
steps in numpy on the CPU either way; a :class:`PolicyMaths` does the three things whose cost
grows with the policy: the per-agent layers built from θ rows, each step's forward and
action draw, and the score-function gradient of ended batches.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from fedhpg.common.batched import mlp


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


class DeviceUnavailable(ValueError):
    """``algo.device`` names a device this machine's torch cannot use."""


def device_problem(engine: str, device: str) -> str | None:
    """Why this machine cannot run ``algo.engine`` on ``algo.device`` (None: it can)."""
    if engine != "torch" or not device.startswith("cuda"):
        return None
    import torch

    if not torch.cuda.is_available():
        return f"{device!r}: torch sees no CUDA device on this machine"
    index = int(device.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        return f"{device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)"
    return None


def maths_for(engine: str, device: str) -> PolicyMaths:
    """The maths of ``algo.engine`` on ``algo.device``."""
    if engine != "torch":
        return NUMPY
    problem = device_problem(engine, device)
    if problem is not None:
        raise DeviceUnavailable(f"algo.device: {problem}")
    from fedhpg.common.batched.torch_maths import TorchMaths

    return TorchMaths(device)
