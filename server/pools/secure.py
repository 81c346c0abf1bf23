"""Secure aggregation over the wire: a private round's four exchanges, the ``Train`` first.

1. ``Train`` (with ``private``, the participants and their channel keys): every agent trains,
   then answers :class:`~fedhpg.common.wire.protocol.MaskKeys` (its fresh round mask key,
   signed with its channel key where agents have a roster); the round policy closes this
   exchange as any round.
2. :class:`~fedhpg.common.wire.protocol.ShareRequest`: every advertised key goes to every
   agent, which checks the signatures, draws the round's graph from the keys and answers
   :class:`~fedhpg.common.wire.protocol.KeyShares` (its secret shares sealed for each
   neighbour).
3. :class:`~fedhpg.common.wire.protocol.MaskRequest`: each agent gets its neighbours' keys and
   the shares sealed for it, and answers its masked contribution
   (:class:`~fedhpg.common.wire.protocol.MaskedUpdate`, with its statistics).
4. :class:`~fedhpg.common.wire.protocol.UnmaskRequest`: who dropped out and whose input is in;
   each included agent answers its revealed shares
   (:class:`~fedhpg.common.wire.protocol.Unmasking`).

Exchanges 2 to 4 close once every live agent asked has answered, or after
``server.round_deadline_s``: an agent that died, or does not answer in time, drops out, and the
protocol (:class:`~fedhpg.common.privacy.secagg.SecAggRound`) rebuilds what the sum needs from
the others' shares. The server keeps only the sum; the updates it returns carry statistics.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy import fixedpoint, masks, shamir
from fedhpg.common.privacy.contribution import EXTRA, RoundPrivacy
from fedhpg.common.privacy.graph import GraphError, round_plan
from fedhpg.common.privacy.secagg import (
    SEALED_BYTES,
    RoundSetup,
    SecAggError,
    SecAggRound,
    fewest_inputs,
)
from fedhpg.common.records.types import RoundResult, UpdateStats
from fedhpg.common.wire import secure_rows as read
from fedhpg.common.wire.protocol import (
    KEY_BYTES,
    KeyShares,
    MaskRequest,
    Request,
    ShareRequest,
    Train,
    Unmasking,
    UnmaskRequest,
)
from fedhpg.common.wire.secure_rows import RowError
from fedhpg.server.pools import RoundAnswers, SecureSum
from fedhpg.server.pools.collection import Collector
from fedhpg.server.pools.links import Links
from fedhpg.server.validation import Reject, Rejection

logger = logging.getLogger(__name__)


def neighbour_count(run: RunConfig, participants: int) -> int:
    """k: how many neighbours each agent of a round of ``participants`` has at most (the
    run's plan for that size; every other agent where the plan cannot be met, which the
    round then reports)."""
    try:
        return round_plan(run.privacy.secagg, participants).neighbours
    except GraphError:
        return max(participants - 1, 0)


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

    def participants(self, links: Links, agents: Sequence[int]) -> list[int]:
        """The agents of ``agents`` that can take part in a secure round: registered, with a
        channel key a secret can be agreed with."""
        return sorted(_channel_keys(links, agents))

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
        statistics, or (``secure.failed``) why it has none."""
        selected = sorted(agents)
        keys = _channel_keys(links, selected)
        participants = sorted(keys)
        secagg = self.run.privacy.secagg
        fewest = fewest_inputs(self.run.privacy.mode, secagg, len(participants))
        outcome = _Outcome(round_index, selected, links.name, len(participants))
        if not participants:
            return outcome.failed("no selected agent is registered")
        try:
            plan = round_plan(secagg, len(participants))
        except GraphError as error:
            return outcome.failed(str(error))
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
        advertised = collector.collect(
            train,
            "round",
            participants,
            pump=pump,
            budgets=budgets,
            while_waiting=while_training,
        )
        adverts: dict[int, tuple[bytes, bytes, bytes]] = {}
        for k, (message, row) in sorted(advertised.answers.items()):
            with outcome.step(k, "mask key"):
                adverts[k] = read.mask_keys(message, row)
        mask_keys = {k: advert[0] for k, advert in adverts.items()}
        if len(mask_keys) < fewest:
            return outcome.failed(f"{len(mask_keys)} agents advertised keys, fewer than {fewest}")
        setup = RoundSetup(
            round=round_index,
            participants=tuple(sorted(mask_keys)),
            channel_keys={k: keys[k] for k in mask_keys},
            mask_keys=mask_keys,
            seed_commitments={k: advert[1] for k, advert in adverts.items()},
            length=self.length,
            neighbours=plan.neighbours,
            threshold=plan.threshold,
        )
        server = SecAggRound(setup)
        owners = list(setup.participants)
        shared = collector.collect(
            ShareRequest(
                round=round_index,
                agents=[],
                participants=owners,
                mask_keys=_rows([adverts[k][0] for k in owners]),
                seed_commitments=_rows([adverts[k][1] for k in owners]),
                signatures=_rows([adverts[k][2] for k in owners]),
            ),
            "key sharing of round",
            owners,
            pump=pump,
            phase=True,
        )
        for k, (message, row) in sorted(shared.answers.items()):
            with outcome.step(k, "key shares"):
                shares = read.key_shares(message, row)
                if shares.mask_key != mask_keys[k]:
                    raise SecAggError("they name another mask key than it advertised")
                server.add_keys(k, shares)
        if len(server.keys) < fewest:
            return outcome.failed(f"{len(server.keys)} agents shared keys, fewer than {fewest}")
        stats = self._masked_inputs(collector, pump, server, setup, outcome)
        dropped, included = server.unmask_request()
        if len(included) < fewest:  # checked before any input is unmasked
            return outcome.failed(_too_few_inputs(len(included), fewest, self.run))
        revealed = collector.collect(
            UnmaskRequest(round=round_index, agents=[], dropped=dropped, included=included),
            "unmasking of round",
            included,
            pump=pump,
            phase=True,
        )
        for k, (message, row) in sorted(revealed.answers.items()):
            with outcome.step(k, "revealed shares"):
                server.add_reveal(k, read.unmasking(message, row))
        try:
            words = server.total(fewest=fewest)
        except SecAggError as error:
            return outcome.failed(f"secure aggregation failed: {error}")
        outcome.unmasked(server)
        scale = fixedpoint.scale_for(len(participants), max(private.bound, 1.0))
        summed = {k: stats[k] for k in server.summed}
        return outcome.answers(
            RoundResult.of_stats(round_index, summed, theta.detach().numpy()),
            SecureSum(
                total=fixedpoint.decode(words, scale),
                inputs=len(server.summed),
                participants=len(participants),
            ),
        )

    def _masked_inputs(
        self,
        collector: Collector,
        pump: Callable[[], None],
        server: SecAggRound,
        setup: RoundSetup,
        outcome: _Outcome,
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
        for k, (message, row) in sorted(masked.answers.items()):
            with outcome.step(k, "masked input"):
                words, kept = read.masked_update(message, row, setup.length)
                server.add_masked(k, words)
                stats[k] = kept
        return stats


class _Outcome:
    """What becomes of one secure round: the agents refused at each step (each logged once,
    recorded in the round's ``failures``) and the answers the coordinator takes."""

    def __init__(
        self, round_index: int, selected: list[int], name: Callable[[int], str], participants: int
    ) -> None:
        self.round = round_index
        self.selected = selected
        self.name = name
        self.participants = participants
        self.refused: dict[int, Rejection] = {}

    @contextlib.contextmanager
    def step(self, agent: int, what: str) -> Iterator[None]:
        """Around taking agent ``agent``'s row: a row refused is the agent's drop-out."""
        try:
            yield
        except (RowError, SecAggError) as error:
            self.refuse(agent, f"its {what} were refused: {error}")

    def refuse(self, agent: int, reason: str) -> None:
        logger.warning("round %d: %s drops out: %s", self.round, self.name(agent), reason)
        self.refused.setdefault(agent, Rejection(Reject.PROTOCOL, reason))

    def unmasked(self, server: SecAggRound) -> None:
        """Log who the unmasking left out, or found revealing wrong shares."""
        for agent, reason in sorted(server.blamed.items()):
            logger.warning(
                "round %d: %s's revealed shares were left out: %s",
                self.round,
                self.name(agent),
                reason,
            )
        for agent, reason in sorted(server.left_out.items()):
            self.refuse(agent, f"its input was left out of the sum: {reason}")

    def failed(self, reason: str) -> RoundAnswers:
        """A round with no sum: θ̃ stays, the coordinator records the round as skipped."""
        return self.answers(
            RoundResult.of_stats(self.round, {}, np.zeros(0, dtype=np.float32)),
            SecureSum(total=np.zeros(0), inputs=0, participants=self.participants, failed=reason),
        )

    def answers(self, result: RoundResult, secure: SecureSum) -> RoundAnswers:
        summed = set(result.agents)
        missing = [self.name(k) for k in self.selected if k not in summed and k not in self.refused]
        if secure.failed is None and (missing or self.refused):
            logger.warning(
                "round %d aggregated %d of %d masked inputs; dropped out: %s",
                self.round,
                len(result),
                len(self.selected),
                ", ".join(missing + [self.name(k) for k in sorted(self.refused)]),
            )
        return RoundAnswers(
            result=result,
            name=self.name,
            failures={self.name(k): r for k, r in sorted(self.refused.items())},
            stragglers=missing,
            secure=secure,
        )


def _rows(values: list[bytes]) -> np.ndarray:
    """Equal-length byte strings as the rows of a uint8 array."""
    return np.frombuffer(b"".join(values), np.uint8).reshape(len(values), -1).copy()


def _channel_keys(links: Links, agents: Sequence[int]) -> dict[int, bytes]:
    """The channel keys of the registered agents of ``agents`` (a key no secret can be agreed
    with leaves its agent out)."""
    keys = {}
    for k in agents:
        peer = links.peers.get(k)
        if peer is None or k not in peer.link.channel_keys:
            continue
        key = bytes(peer.link.channel_keys[k])
        if masks.usable_public_key(key):
            keys[k] = key
        else:
            logger.warning(
                "%s's channel key agrees on no secret: it cannot aggregate", links.name(k)
            )
    return keys


def _too_few_inputs(arrived: int, fewest: int, run: RunConfig) -> str:
    if run.privacy.mode == "dp_secagg":
        return (
            f"{arrived} masked inputs arrived, fewer than the {fewest} whose noise shares reach "
            "σC (privacy.secagg.dropout): nothing was unmasked"
        )
    return "no masked input arrived"


__all__ = ["KeyShares", "SecureExchange", "Unmasking", "row_bytes"]
