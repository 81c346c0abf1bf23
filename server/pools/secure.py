"""Secure aggregation over the wire: a private round's three exchanges after the ``Train``.

1. ``Train`` (with ``private``, the participants and their channel keys): every agent trains,
   then answers :class:`~fedhpg.common.wire.protocol.KeyShares` (its round mask key, its secret
   shares sealed for each neighbour); the round policy closes this exchange as any round.
2. :class:`~fedhpg.common.wire.protocol.MaskRequest`: each agent gets its neighbours' keys and
   the shares sealed for it, and answers its masked contribution
   (:class:`~fedhpg.common.wire.protocol.MaskedUpdate`, with its statistics).
3. :class:`~fedhpg.common.wire.protocol.UnmaskRequest`: who dropped out and whose input is in;
   each included agent answers its revealed shares
   (:class:`~fedhpg.common.wire.protocol.Unmasking`).

Exchanges 2 and 3 close once every live agent asked has answered, or after
``server.round_deadline_s``: an agent that died, or does not answer in time, drops out, and the
protocol (:class:`~fedhpg.common.privacy.secagg.SecAggRound`) rebuilds what the sum needs from
the others' shares. The server keeps only the sum; the updates it returns carry statistics.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from fedhpg.common.config import RunConfig
from fedhpg.common.privacy import fixedpoint, shamir
from fedhpg.common.privacy.contribution import EXTRA, RoundPrivacy
from fedhpg.common.privacy.secagg import (
    SEALED_BYTES,
    Revealed,
    RoundSetup,
    SecAggError,
    SecAggRound,
)
from fedhpg.common.privacy.secagg import (
    KeyShares as Shares,
)
from fedhpg.common.types import AgentUpdate, UpdateStats
from fedhpg.common.wire.protocol import (
    KEY_BYTES,
    KeyShares,
    MaskedUpdate,
    MaskRequest,
    Request,
    Train,
    Unmasking,
    UnmaskRequest,
)
from fedhpg.server.pools import FederationError, RoundAnswers, SecureSum
from fedhpg.server.pools.collection import Collector
from fedhpg.server.pools.links import Links

logger = logging.getLogger(__name__)


def neighbour_count(run: RunConfig, participants: int) -> int:
    """k: how many neighbours each agent of a round of ``participants`` has at most."""
    others = max(participants - 1, 0)
    chosen = run.privacy.secagg.neighbours
    return others if chosen is None else min(others, 2 * ((chosen + 1) // 2))


def row_bytes(run: RunConfig, num_params: int) -> int:
    """The largest row one agent sends in a secure round of all K agents (its key shares,
    its masked input with statistics, or its revealed shares)."""
    k = neighbour_count(run, run.agents.num_agents)
    return max(
        KEY_BYTES + k * (8 + SEALED_BYTES),
        8 * (num_params + EXTRA) + 3 * 1024,
        k * (8 + 1 + shamir.SHARE_BYTES),
    )


class SecureExchange:
    """The server's side of a run's secure rounds over a :class:`Collector`."""

    def __init__(self, run: RunConfig, num_params: int) -> None:
        self.run = run
        self.length = num_params + EXTRA
        self.answer_bytes = row_bytes(run, num_params)

    def round(
        self,
        collector: Collector,
        links: Links,
        pump: Callable[[], None],
        round_index: int,
        theta: torch.Tensor,
        agents: Sequence[int],
        private: RoundPrivacy,
        *,
        budgets: Mapping[int, Mapping[str, int]] | None = None,
        while_training: Callable[[], None] | None = None,
    ) -> RoundAnswers:
        """One round's training and secure aggregation; its sum and the included agents'
        statistics."""
        selected = sorted(agents)
        keys = {
            k: peer.link.channel_keys[k]
            for k in selected
            if (peer := links.peers.get(k)) is not None and k in peer.link.channel_keys
        }
        participants = sorted(keys)
        if not participants:
            raise FederationError(f"round {round_index}: no selected agent is registered")
        secagg = self.run.privacy.secagg
        setup = RoundSetup(
            round=round_index,
            participants=tuple(participants),
            channel_keys=keys,
            length=self.length,
            threshold=secagg.threshold,
            neighbours=secagg.neighbours,
        )
        server = SecAggRound(setup)
        train = Train(
            round=round_index,
            theta=theta.detach().numpy(),
            agents=[],
            private=private,
            participants=participants,
            channel_keys=np.frombuffer(b"".join(keys[k] for k in participants), np.uint8)
            .reshape(len(participants), KEY_BYTES)
            .copy(),
        )
        shared = collector.collect(
            train,
            "round",
            participants,
            pump=pump,
            budgets=budgets,
            while_waiting=while_training,
        )
        for k, (message, row) in sorted(shared.answers.items()):
            sealed = {
                int(v): bytes(message.sealed[row, j])
                for j, v in enumerate(message.recipients[row])
                if v >= 0
            }
            try:
                server.add_keys(k, Shares(mask_key=bytes(message.mask_keys[row]), sealed=sealed))
            except SecAggError as error:
                logger.warning("round %d: %s drops out: %s", round_index, links.name(k), error)
        stats = self._masked_inputs(collector, pump, server, setup)
        dropped, included = server.unmask_request()
        if not included:
            raise FederationError(f"round {round_index}: no masked input arrived")
        revealed = collector.collect(
            UnmaskRequest(round=round_index, agents=[], dropped=dropped, included=included),
            "unmasking of round",
            included,
            pump=pump,
            phase=True,
        )
        for k, (message, row) in sorted(revealed.answers.items()):
            server.add_reveal(
                k,
                {
                    int(owner): (Revealed(int(kind)), bytes(message.shares[row, j]))
                    for j, (owner, kind) in enumerate(
                        zip(message.owners[row], message.kinds[row], strict=True)
                    )
                    if owner >= 0 and kind in (Revealed.MASK_KEY, Revealed.SELF_SEED)
                },
            )
        try:
            words = server.total()
        except SecAggError as error:
            raise FederationError(f"secure aggregation failed: {error}") from None
        scale = fixedpoint.scale_for(len(participants), max(private.bound, 1.0))
        missing = [links.name(k) for k in selected if k not in server.inputs]
        if missing:
            logger.warning(
                "round %d aggregated %d of %d masked inputs; dropped out: %s",
                round_index,
                len(included),
                len(selected),
                ", ".join(missing),
            )
        return RoundAnswers(
            updates=[
                AgentUpdate(agent_index=k, agent_id=links.name(k), theta=theta, stats=stats[k])
                for k in included
            ],
            stragglers=missing,
            secure=SecureSum(total=fixedpoint.decode(words, scale), inputs=len(included)),
        )

    def _masked_inputs(
        self,
        collector: Collector,
        pump: Callable[[], None],
        server: SecAggRound,
        setup: RoundSetup,
    ) -> dict[int, UpdateStats]:
        """Exchange 2: the routed keys and shares out, the masked inputs in."""
        width = max((len(setup.graph[k]) for k in server.keys), default=0)

        def rows_for(owed: list[int]) -> Request:
            senders = np.full((len(owed), width), -1, dtype=np.int64)
            mask_keys = np.zeros((len(owed), width, KEY_BYTES), dtype=np.uint8)
            sealed = np.zeros((len(owed), width, SEALED_BYTES), dtype=np.uint8)
            for i, k in enumerate(owed):
                keys, shares = server.routed(k)
                for j, v in enumerate(sorted(keys)):
                    senders[i, j] = v
                    mask_keys[i, j] = np.frombuffer(keys[v], dtype=np.uint8)
                    sealed[i, j] = np.frombuffer(shares[v], dtype=np.uint8)
            return MaskRequest(
                round=setup.round, agents=owed, senders=senders, mask_keys=mask_keys, sealed=sealed
            )

        template = MaskRequest(
            round=setup.round,
            agents=[],
            senders=np.zeros((0, 0), dtype=np.int64),
            mask_keys=np.zeros((0, 0, KEY_BYTES), dtype=np.uint8),
            sealed=np.zeros((0, 0, SEALED_BYTES), dtype=np.uint8),
        )
        masked = collector.collect(
            template,
            "masking of round",
            sorted(server.keys),
            pump=pump,
            rows_for=rows_for,
            phase=True,
        )
        stats: dict[int, UpdateStats] = {}
        records: dict[int, list[UpdateStats]] = {}
        for k, (message, row) in sorted(masked.answers.items()):
            assert isinstance(message, MaskedUpdate)
            words = np.ascontiguousarray(message.masked[row]).view(np.uint64)
            try:
                server.add_masked(k, words)
            except SecAggError as error:
                logger.warning("round %d: agent %d drops out: %s", setup.round, k, error)
                continue
            if id(message) not in records:
                records[id(message)] = message.stats.records()
            stats[k] = records[id(message)][row]
        return stats


__all__ = ["KeyShares", "SecureExchange", "Unmasking", "row_bytes"]
