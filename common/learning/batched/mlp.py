"""The layer sizes of the tanh MLP categorical policy, and where each layer sits in θ.

The flat θ layout is torch's: for each ``nn.Linear`` its weight [out, in] row-major, then its
bias [out], layer after layer (common/learning/policies.py's MLPCategoricalPolicy): what the
compiled backend's kernels read.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass


@dataclass(frozen=True)
class MLPShape:
    """Layer sizes [obs_dim, *hidden, num_actions] of the flat parameter vector."""

    sizes: tuple[int, ...]

    @property
    def layers(self) -> list[tuple[int, int, int]]:
        """(offset, in, out) of each layer's weight; its bias follows the weight."""
        out, offset = [], 0
        for n_in, n_out in itertools.pairwise(self.sizes):
            out.append((offset, n_in, n_out))
            offset += n_in * n_out + n_out
        return out

    @property
    def num_params(self) -> int:
        return sum(n_in * n_out + n_out for _, n_in, n_out in self.layers)
