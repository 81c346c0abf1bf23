"""numpy views of host tensors that a round reads again and again.

A round's budgets and per-row constants are the same tensors every iteration (and every
round that repeats its agents), and its θ rows one tensor stepped in place; the compiled
backend and the round's tally read them as numpy arrays. Taking a tensor's array is a torch
call, and on a CPU whose caches another process has just filled (an agent among others, a
host's round between messages) each such call costs several microseconds more than the
numpy it saves: a lone agent's round is made of a few dozen of them. :class:`HostArrays`
takes each tensor's view once and hands the same array back while the tensor is the same
object: a view shares the tensor's memory, so it reads what the tensor holds now.
"""

from __future__ import annotations

import numpy as np
import torch

KEPT = 32
"""Views a :class:`HostArrays` holds; when full it starts over."""


class HostArrays:
    """The numpy view of each host tensor asked for, kept while the tensor is alive here (the
    tensor is held with its view, so its identity cannot be reused meanwhile)."""

    def __init__(self) -> None:
        self._kept: dict[int, tuple[torch.Tensor, np.ndarray]] = {}

    def __call__(self, tensor: torch.Tensor) -> np.ndarray:
        """``tensor``'s values as an array that shares its memory (``tensor`` on the CPU)."""
        kept = self._kept.get(id(tensor))
        if kept is not None and kept[0] is tensor:
            return kept[1]
        if len(self._kept) >= KEPT:
            self._kept.clear()
        array = tensor.detach().numpy()
        self._kept[id(tensor)] = (tensor, array)
        return array
