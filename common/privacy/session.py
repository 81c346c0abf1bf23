"""The agents' side of secure aggregation for a range of logical agents of one run: each
agent's long-lived channel key pair and its round state (:class:`~.secagg.SecAggAgent`), the
round's public setup, and each agent's noise stream. An agent program (a host of many) and
the in-process pool hold one each; masks are between logical agents, also on one host.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy import dp
from fedhpg.common.privacy.graph import GraphError, round_plan
from fedhpg.common.privacy.secagg import RoundSetup, SecAggAgent, SecAggError
from fedhpg.common.privacy.signing import (
    SIGNATURE_BYTES,
    AgentSigning,
    SignatureError,
    mask_statement,
    sign,
)


class LocalSecAgg:
    """The secure aggregation state of the logical agents this process serves, and what it
    signs with and checks against (:mod:`.signing`; None: unsigned)."""

    def __init__(self, run: RunConfig, signing: AgentSigning | None = None) -> None:
        self.settings = run.privacy
        self.signing = signing
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

    def advertise(self, round_index: int, index: int) -> tuple[bytes, bytes, bytes]:
        """Agent ``index``'s fresh mask key for the round, its seed commitment, and its
        signature of both with the agent's channel key (64 zero bytes where this process has
        no roster)."""
        agent = self.agent(index)
        mask_key = agent.advertise(round_index)
        commitment = agent.seed_commitment(round_index)
        if self.signing is None:
            return mask_key, commitment, bytes(SIGNATURE_BYTES)
        statement = mask_statement(round_index, index, mask_key, agent.channel_public, commitment)
        return mask_key, commitment, sign(self.signing.private, statement)

    def setup(
        self,
        round_index: int,
        planned: int,
        length: int,
        channel_keys: Mapping[int, bytes],
        mask_keys: Mapping[int, bytes],
        seed_commitments: Mapping[int, bytes],
        signatures: Mapping[int, bytes] | None = None,
    ) -> RoundSetup:
        """The round's public setup once its mask keys are advertised: the graph and
        threshold of a round of ``planned`` agents (the participants the server named) over
        those that advertised. With a roster, every advertised key must carry its agent's
        signature (SecAggError: this process refuses the round)."""
        if not set(mask_keys) <= set(channel_keys) or set(seed_commitments) != set(mask_keys):
            raise SecAggError(f"round {round_index}: keys of agents with no channel key")
        if self.signing is not None:
            roster = self.signing.roster
            for v, key in mask_keys.items():
                statement = mask_statement(
                    round_index, v, key, channel_keys[v], seed_commitments[v]
                )
                try:
                    roster.check(v, statement, (signatures or {}).get(v, b""))
                except SignatureError as error:
                    raise SecAggError(
                        f"round {round_index}: the server relayed keys its agent did not sign: "
                        f"{error}"
                    ) from None
        try:
            plan = round_plan(self.settings.secagg, planned)
        except GraphError as error:
            raise SecAggError(f"round {round_index}: {error}") from None
        return RoundSetup(
            round=round_index,
            participants=tuple(sorted(mask_keys)),
            channel_keys={v: channel_keys[v] for v in mask_keys},
            mask_keys=dict(mask_keys),
            seed_commitments=dict(seed_commitments),
            length=length,
            neighbours=plan.neighbours,
            threshold=plan.threshold,
        )

    def noise(self, round_index: int, agent: int) -> dp.NoiseSource:
        """Agent ``agent``'s share of the DP noise in a round."""
        return dp.noise_stream(
            self.settings.noise_seed, round_index, agent, secure=self.settings.secure_noise_on
        )
