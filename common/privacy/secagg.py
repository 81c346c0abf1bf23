"""Secure aggregation (Bonawitz et al., CCS 2017) with SecAgg+'s neighbour graph (Bell et al.,
CCS 2020): the server learns the sum of the round's inputs and nothing else about any one of
them, and the round completes although agents drop out along the way.

The rounds of one aggregation, each agent's and the server's side (no wire here: the pools
and the agent program carry these values in their messages):

0. Before: every agent has a long-lived channel key pair (X25519), its public half registered
   with the server. The round's :class:`RoundSetup` names the participants and their channel
   keys, and which of them are each one's neighbours (everyone, or k of them: SecAgg+).
1. :meth:`SecAggAgent.share_keys`: a fresh mask key pair and self-mask seed b_u for the round;
   t-of-k Shamir shares of both secrets, one pair for each neighbour, sealed (AES-GCM) under
   the channel key of that pair. Sent: the mask public key and the sealed shares (U1: those
   whose keys arrived).
2. :meth:`SecAggRound.routed` gives each agent its neighbours' mask keys and the shares sealed
   for it; :meth:`SecAggAgent.mask` opens them and sends y_u = x_u + PRG(b_u) + Σ_{v>u} PRG(s_uv)
   − Σ_{v<u} PRG(s_uv) modulo 2⁶⁴, s_uv agreed from the pair's mask keys (U2: inputs that
   arrived).
3. :meth:`SecAggRound.unmask_request` names who dropped after sharing (U1 \\ U2) and whose
   inputs are in (U2); :meth:`SecAggAgent.reveal` answers with its shares of the dropped
   neighbours' mask keys and of the included neighbours' self-mask seeds, never both for one
   agent. :meth:`SecAggRound.total` rebuilds from t shares each what the sum must lose: every
   included agent's PRG(b_u), every pairwise mask between an included and a dropped agent.

The sum is exactly Σ_{u∈U2} x_u modulo 2⁶⁴. An honest agent refuses a round in which fewer
than t of its neighbours take part at any step (the server could otherwise ask for both of
one agent's secrets). Against a server that follows the protocol and any agents but fewer
than t of each neighbourhood colluding with it, one input stays hidden; a server that lies
about the channel keys (no public-key infrastructure here) is outside this model.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import struct
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from fedhpg.common.privacy import fixedpoint, masks, shamir

SHARE_PLAINTEXT = struct.Struct("<qqq")
"""A sealed share's header: sender, receiver, round; then the two shares."""
SEALED_BYTES = masks.NONCE_BYTES + SHARE_PLAINTEXT.size + 2 * shamir.SHARE_BYTES + masks.TAG_BYTES


class SecAggError(RuntimeError):
    """A round that cannot go on: too few agents or shares, or a value that does not fit."""


class Revealed(IntEnum):
    """What a revealed share is a share of."""

    MASK_KEY = 1
    """A dropped agent's mask private key: its pairwise masks are rebuilt."""
    SELF_SEED = 2
    """An included agent's self-mask seed b_u: its self mask is removed."""


@dataclass(frozen=True, kw_only=True)
class RoundSetup:
    """What everyone knows of a round before it starts."""

    round: int
    participants: tuple[int, ...]
    """The agents asked, in increasing order."""
    channel_keys: Mapping[int, bytes]
    """Each participant's channel public key."""
    length: int
    """Words in each input."""
    threshold: float = 0.5
    """t = ⌊threshold · k⌋ + 1 shares of an agent's k rebuild its secrets."""
    neighbours: int | None = None
    """k: how many others each agent masks with (SecAgg+); None, or k ≥ n − 1: all (SecAgg)."""

    @functools.cached_property
    def graph(self) -> dict[int, tuple[int, ...]]:
        """Each participant's neighbours: every other one, or its k nearest on a ring in an
        order drawn from the round (public: every side computes the same)."""
        people = list(self.participants)
        count = len(people)
        if self.neighbours is None or self.neighbours >= count - 1:
            return {u: tuple(v for v in people if v != u) for u in people}
        ring = sorted(
            people,
            key=lambda u: hashlib.sha256(struct.pack("<qq", self.round, u)).digest(),
        )
        half = math.ceil(self.neighbours / 2)
        graph: dict[int, tuple[int, ...]] = {}
        for position, u in enumerate(ring):
            near = {ring[(position + step) % count] for step in range(-half, half + 1)} - {u}
            graph[u] = tuple(sorted(near))
        return graph

    def threshold_of(self, agent: int) -> int:
        """t of ``agent``'s neighbourhood."""
        degree = len(self.graph[agent])
        return min(math.floor(self.threshold * degree) + 1, degree)


def share_point(agent: int) -> int:
    """The Shamir x-coordinate of the share an agent holds (never 0)."""
    return agent + 1


def _associated(setup: RoundSetup, sender: int, receiver: int) -> bytes:
    return SHARE_PLAINTEXT.pack(sender, receiver, setup.round)


@dataclass(frozen=True, kw_only=True)
class KeyShares:
    """An agent's step 1: its round mask public key and its shares sealed for each neighbour."""

    mask_key: bytes
    sealed: Mapping[int, bytes]


@dataclass(kw_only=True)
class _AgentRound:
    setup: RoundSetup
    mask_private: bytes
    self_seed: bytes
    held: dict[int, tuple[bytes, bytes]] = field(default_factory=dict)
    """Neighbour → (share of its mask key, share of its self-mask seed)."""
    masked_with: frozenset[int] = frozenset()
    revealed: bool = False


class SecAggAgent:
    """One logical agent's side: its channel key pair, and the round in progress."""

    def __init__(self, index: int, channel_private: bytes | None = None) -> None:
        self.index = index
        self.channel_private = channel_private or masks.new_private_key()
        self.channel_public = masks.public_key(self.channel_private)
        self._channels: dict[tuple[int, int, bytes], bytes] = {}
        self._round: _AgentRound | None = None

    def _channel(self, sender: int, receiver: int, peer_public: bytes) -> bytes:
        key = (sender, receiver, peer_public)
        if key not in self._channels:
            self._channels[key] = masks.agree(
                self.channel_private, peer_public, masks.channel_purpose(sender, receiver)
            )
        return self._channels[key]

    def share_keys(self, setup: RoundSetup) -> KeyShares:
        """Step 1: a fresh mask key pair and self-mask seed, and their shares for each
        neighbour, sealed for it."""
        if self.index not in setup.graph:
            raise SecAggError(f"agent {self.index} is not a participant of round {setup.round}")
        neighbours = setup.graph[self.index]
        threshold = setup.threshold_of(self.index)
        state = _AgentRound(
            setup=setup, mask_private=masks.new_private_key(), self_seed=os.urandom(32)
        )
        points = [share_point(v) for v in neighbours]
        key_shares = shamir.split(state.mask_private, points, threshold)
        seed_shares = shamir.split(state.self_seed, points, threshold)
        sealed = {}
        for v, key_share, seed_share in zip(neighbours, key_shares, seed_shares, strict=True):
            channel = self._channel(self.index, v, setup.channel_keys[v])
            plaintext = _associated(setup, self.index, v) + key_share + seed_share
            sealed[v] = masks.seal(channel, plaintext, _associated(setup, self.index, v))
        self._round = state
        return KeyShares(mask_key=masks.public_key(state.mask_private), sealed=sealed)

    def mask(
        self,
        round_index: int,
        inputs: np.ndarray,
        mask_keys: Mapping[int, bytes],
        sealed: Mapping[int, bytes],
    ) -> np.ndarray:
        """Step 2: ``inputs`` (uint64 words) masked with the self mask and a pairwise mask with
        each neighbour whose keys arrived (``mask_keys``), whose sealed shares it keeps."""
        state = self._state(round_index)
        setup = state.setup
        if inputs.shape != (setup.length,) or inputs.dtype != np.uint64:
            raise SecAggError(f"an input is {setup.length} uint64 words, got {inputs.shape}")
        present = set(mask_keys)
        if not present <= set(setup.graph[self.index]) or set(sealed) != present:
            raise SecAggError("the server routed keys or shares of agents that are not neighbours")
        threshold = setup.threshold_of(self.index)
        if len(present) < threshold:
            raise SecAggError(
                f"round {round_index}: {len(present)} of agent {self.index}'s neighbours shared "
                f"keys, fewer than the threshold {threshold}"
            )
        for v in sorted(present):
            channel = self._channel(v, self.index, setup.channel_keys[v])
            plaintext = masks.open_sealed(channel, sealed[v], _associated(setup, v, self.index))
            header, rest = plaintext[: SHARE_PLAINTEXT.size], plaintext[SHARE_PLAINTEXT.size :]
            if header != _associated(setup, v, self.index):
                raise SecAggError(f"a share from agent {v} names another round or agent")
            state.held[v] = (rest[: shamir.SHARE_BYTES], rest[shamir.SHARE_BYTES :])
        masked = inputs.copy()
        fixedpoint.add(masked, masks.expand(state.self_seed, setup.length))
        for v in sorted(present):
            fixedpoint_step = fixedpoint.add if v > self.index else fixedpoint.subtract
            fixedpoint_step(
                masked, _pair_mask(state.mask_private, mask_keys[v], setup, self.index, v)
            )
        state.masked_with = frozenset(present)
        return masked

    def reveal(
        self, round_index: int, dropped: Collection[int], included: Collection[int]
    ) -> dict[int, tuple[Revealed, bytes]]:
        """Step 3: for each neighbour it masked with, the share of its mask key (it dropped)
        or of its self-mask seed (its input is in the sum); never both, never twice."""
        state = self._state(round_index)
        dropped, included = set(dropped), set(included)
        if state.revealed:
            raise SecAggError(f"round {round_index}: agent {self.index} already revealed")
        if dropped & included or self.index not in included:
            raise SecAggError("an unmasking request must name disjoint sets, this agent included")
        if not (dropped | included) >= state.masked_with:
            raise SecAggError("an unmasking request must account for every neighbour masked with")
        threshold = state.setup.threshold_of(self.index)
        if len(state.masked_with & included) + 1 < threshold:  # + 1: itself
            raise SecAggError(
                f"round {round_index}: fewer than {threshold} of agent {self.index}'s "
                "neighbourhood sent inputs"
            )
        state.revealed = True
        answer: dict[int, tuple[Revealed, bytes]] = {}
        for v in sorted(state.masked_with):
            key_share, seed_share = state.held[v]
            if v in dropped:
                answer[v] = (Revealed.MASK_KEY, key_share)
            else:
                answer[v] = (Revealed.SELF_SEED, seed_share)
        return answer

    def _state(self, round_index: int) -> _AgentRound:
        state = self._round
        if state is None or state.setup.round != round_index:
            raise SecAggError(f"agent {self.index} has no keys for round {round_index}")
        return state


def _pair_mask(private: bytes, peer_public: bytes, setup: RoundSetup, u: int, v: int) -> np.ndarray:
    """PRG(s_uv): the words both agents of a pair derive from their mask keys."""
    seed = masks.agree(private, peer_public, masks.mask_purpose(setup.round, u, v))
    return masks.expand(seed, setup.length)


class SecAggRound:
    """The server's side of one aggregation: it routes, collects and unmasks, never sees an
    input alone."""

    def __init__(self, setup: RoundSetup) -> None:
        self.setup = setup
        self.keys: dict[int, KeyShares] = {}
        """U1: who shared keys."""
        self.inputs: dict[int, np.ndarray] = {}
        """U2: the masked inputs that arrived."""
        self.reveals: dict[int, dict[int, tuple[Revealed, bytes]]] = {}
        """U3: who answered the unmasking request."""

    def add_keys(self, agent: int, shares: KeyShares) -> None:
        neighbours = set(self.setup.graph.get(agent, ()))
        if agent not in self.setup.graph or set(shares.sealed) != neighbours:
            raise SecAggError(f"agent {agent}'s key shares do not match its neighbours")
        if any(len(c) != SEALED_BYTES for c in shares.sealed.values()):
            raise SecAggError(f"agent {agent}'s sealed shares are not {SEALED_BYTES} bytes")
        self.keys[agent] = shares

    def routed(self, agent: int) -> tuple[dict[int, bytes], dict[int, bytes]]:
        """For ``agent`` (in U1): its neighbours' mask keys and the shares they sealed for it,
        of those neighbours that shared keys."""
        present = [v for v in self.setup.graph[agent] if v in self.keys]
        return (
            {v: self.keys[v].mask_key for v in present},
            {v: self.keys[v].sealed[agent] for v in present},
        )

    def add_masked(self, agent: int, masked: np.ndarray) -> None:
        if agent not in self.keys:
            raise SecAggError(f"agent {agent} sent an input without having shared keys")
        if masked.shape != (self.setup.length,):
            raise SecAggError(f"agent {agent}'s input is not {self.setup.length} words")
        self.inputs[agent] = np.asarray(masked, dtype=np.uint64)

    def unmask_request(self) -> tuple[list[int], list[int]]:
        """(dropped: shared keys but sent no input, included: sent an input)."""
        return sorted(set(self.keys) - set(self.inputs)), sorted(self.inputs)

    def add_reveal(self, agent: int, shares: Mapping[int, tuple[Revealed, bytes]]) -> None:
        if agent not in self.inputs:
            raise SecAggError(f"agent {agent} revealed shares without an input in the sum")
        self.reveals[agent] = dict(shares)

    def total(self) -> np.ndarray:
        """Σ x_u over the included agents, modulo 2⁶⁴; SecAggError when some secret has fewer
        than t shares among the answers."""
        setup = self.setup
        dropped, included = self.unmask_request()
        if not included:
            raise SecAggError(f"round {setup.round}: no masked input arrived")
        collected: dict[tuple[int, Revealed], dict[int, bytes]] = {}
        for holder, shares in self.reveals.items():
            for owner, (kind, share) in shares.items():
                collected.setdefault((owner, kind), {})[share_point(holder)] = share
        total = np.zeros(setup.length, dtype=np.uint64)
        for u in included:
            fixedpoint.add(total, self.inputs[u])
            seed = self._secret(collected, u, Revealed.SELF_SEED)
            fixedpoint.subtract(total, masks.expand(seed, setup.length))
        for v in dropped:
            partners = [u for u in setup.graph[v] if u in self.inputs]
            if not partners:
                continue
            private = self._secret(collected, v, Revealed.MASK_KEY)
            for u in partners:
                # u added +PRG(s_uv) for v > u, −PRG(s_uv) for v < u: take it back out
                step = fixedpoint.subtract if v > u else fixedpoint.add
                step(total, _pair_mask(private, self.keys[u].mask_key, setup, v, u))
        return total

    def _secret(
        self, collected: Mapping[tuple[int, Revealed], dict[int, bytes]], owner: int, kind: Revealed
    ) -> bytes:
        shares = collected.get((owner, kind), {})
        threshold = self.setup.threshold_of(owner)
        if len(shares) < threshold:
            raise SecAggError(
                f"round {self.setup.round}: {len(shares)} share(s) of agent {owner}'s "
                f"{kind.name.lower().replace('_', ' ')}, fewer than the threshold {threshold}"
            )
        return shamir.combine(shares, threshold)
