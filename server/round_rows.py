"""A round's accepted θ_k, gathered as they arrive into the one [K, d] matrix strategies use.

At d = 10⁴ and K = 1,000 the round's updates are 40 MB: copied once, from the received frames
into their agent's row (the frames are then let go), while other hosts still train. Rows are
in agent-index order, the round result's; the matrix is 64-byte aligned, as torch allocates
its own.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

ALIGNMENT = 64
"""Bytes: torch's CPU allocator aligns every tensor so (a torch.stack's result included)."""


def aligned_empty(rows: int, columns: int) -> np.ndarray:
    """An uninitialised float32 [rows, columns] array whose data starts on ALIGNMENT bytes.

    numpy, not torch, allocates it: numpy asks the kernel for huge pages for large arrays,
    and faulting a large array in 4 KiB pages costs several times the copy into it."""
    nbytes = rows * columns * 4
    raw = np.empty(nbytes + ALIGNMENT, dtype=np.uint8)
    start = -raw.ctypes.data % ALIGNMENT
    return raw[start : start + nbytes].view(np.float32).reshape(rows, columns)


def _runs(pairs: Sequence[tuple[int, int]]) -> Iterable[tuple[int, int, int]]:
    """(source row, destination row, length) of each run of ``pairs`` in which both rows
    step by one: a batch usually lands as one or two slices, not row by row."""
    start = 0
    for i in range(1, len(pairs) + 1):
        if (
            i == len(pairs)
            or pairs[i][0] != pairs[i - 1][0] + 1
            or pairs[i][1] != pairs[i - 1][1] + 1
        ):
            yield pairs[start][0], pairs[start][1], i - start
            start = i


class RoundRows:
    """One row per agent asked to train this round, in agent-index order."""

    def __init__(self, agents: Iterable[int], num_params: int) -> None:
        self.place = {index: row for row, index in enumerate(sorted(agents))}
        self.matrix = aligned_empty(len(self.place), num_params)

    def put(self, indices: Sequence[int], thetas: np.ndarray, rows: Sequence[int]) -> None:
        """Copy ``thetas[rows[j]]`` into agent ``indices[j]``'s row."""
        pairs = sorted(zip(rows, (self.place[k] for k in indices), strict=True))
        for source, target, length in _runs(pairs):
            self.matrix[target : target + length] = thetas[source : source + length]

    def block(self, accepted: Sequence[int]) -> np.ndarray:
        """The [len(accepted), d] matrix of the accepted agents' rows (ascending indices):
        the matrix itself when every agent asked was accepted, else a compact copy."""
        if len(accepted) == len(self.place):
            return self.matrix
        compact = aligned_empty(len(accepted), self.matrix.shape[1])
        np.take(self.matrix, [self.place[k] for k in accepted], axis=0, out=compact)
        return compact
