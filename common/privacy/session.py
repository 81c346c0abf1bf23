"""The agents' side of secure aggregation for a range of logical agents of one run: each
agent's long-lived channel key pair and its round state (:class:`~.secagg.SecAggAgent`), the
round's public setup, and each agent's noise stream. An agent program (a host of many) and
the in-process pool hold one each; masks are between logical agents, also on one host.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from fedhpg.common.config import RunConfig
from fedhpg.common.privacy import dp
from fedhpg.common.privacy.secagg import RoundSetup, SecAggAgent


class LocalSecAgg:
    """The secure aggregation state of the logical agents this process serves."""

    def __init__(self, run: RunConfig) -> None:
        self.settings = run.privacy
        self._agents: dict[int, SecAggAgent] = {}

    def agent(self, index: int) -> SecAggAgent:
        """Agent ``index``'s side, its channel key pair made on first use."""
        if index not in self._agents:
            self._agents[index] = SecAggAgent(index)
        return self._agents[index]

    def channel_keys(self, indices: Sequence[int]) -> np.ndarray:
        """The channel public keys of ``indices`` as rows of a [n, 32] uint8 array."""
        keys = b"".join(self.agent(k).channel_public for k in indices)
        return np.frombuffer(keys, dtype=np.uint8).reshape(len(indices), 32).copy()

    def setup(
        self,
        round_index: int,
        participants: Sequence[int],
        length: int,
        channel_keys: Mapping[int, bytes] | None = None,
    ) -> RoundSetup:
        """The round's public setup (``channel_keys``: as the server sent them; None: this
        process's own agents', in process)."""
        keys = (
            dict(channel_keys)
            if channel_keys is not None
            else {k: self.agent(k).channel_public for k in participants}
        )
        return RoundSetup(
            round=round_index,
            participants=tuple(sorted(participants)),
            channel_keys=keys,
            length=length,
            threshold=self.settings.secagg.threshold,
            neighbours=self.settings.secagg.neighbours,
        )

    def noise(self, round_index: int, agent: int) -> dp.NoiseSource:
        """Agent ``agent``'s share of the DP noise in a round."""
        return dp.noise_stream(
            self.settings.noise_seed, round_index, agent, secure=self.settings.secure_noise_on
        )
