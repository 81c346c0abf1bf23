"""Secure aggregation (Bonawitz et al., CCS 2017) with SecAgg+'s neighbour graph (Bell et al.,
CCS 2020): the server learns the sum of the round's inputs and nothing else about any one of
them, and the round completes although agents drop out along the way.

The rounds of one aggregation, each agent's and the server's side (no wire here: the pools
and the agent program carry these values in their messages):

0. Before: every agent has a long-lived channel key pair (X25519), its public half registered
   with the server. :meth:`SecAggAgent.advertise`: a fresh mask key pair and self-mask seed
   b_u for the round; the mask public key is advertised (signed where agents have a roster:
   :mod:`.signing`). The round's :class:`RoundSetup` names those that advertised, their keys,
   and each one's neighbours: every other, or k of them on a ring drawn from all the
   advertised keys (SecAgg+, :mod:`.graph`), with the threshold t of the round's plan.
1. :meth:`SecAggAgent.share_keys`: t-of-k Shamir shares of both secrets, one pair for each
   neighbour, sealed (AES-GCM) under the channel key of that pair (U1: those whose shares
   arrived).
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
than t of its neighbours take part at any step, and answers one unmasking request a round:
a server asking some neighbours for one secret and others for the other gets t shares of both
only with 2t − k colluding neighbours, which the round's plan makes improbable (:mod:`.graph`).
With a roster, a server that substitutes keys is caught by the agents; without one, the server
is trusted to relay the keys it was sent.
"""

from __future__ import annotations

import functools
import hashlib
import os
import struct
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from fedhpg.common.configuration.settings.privacy import SecAggConfig
from fedhpg.common.privacy import fixedpoint, masks, shamir
from fedhpg.common.privacy.graph import Tolerance, graph_seed, neighbour_graph

SHARE_PLAINTEXT = struct.Struct("<qqq")
"""A sealed share's header: sender, receiver, round; then the two shares."""
SEALED_BYTES = masks.NONCE_BYTES + SHARE_PLAINTEXT.size + 2 * shamir.SHARE_BYTES + masks.TAG_BYTES


class SecAggError(RuntimeError):
    """A round that cannot go on: too few agents or shares, or a value that does not fit."""


def fewest_inputs(mode: str, settings: SecAggConfig, participants: int) -> int:
    """The fewest inputs a round of ``participants`` may unmask: with distributed noise
    (``dp_secagg``), enough that the honest ones among them (all but the colluders the round
    tolerates) carry :func:`noise_shares` shares of the noise; otherwise one."""
    if mode != "dp_secagg":
        return 1
    colluders = Tolerance(corruption=settings.corruption, dropout=settings.dropout).colluders(
        participants
    )
    return min(participants, noise_shares(settings, participants) + colluders)


def noise_shares(settings: SecAggConfig, participants: int) -> int:
    """How many agents' noise a ``dp_secagg`` round's sum is sure to hold against the server
    and the agents colluding with it (they know, and can remove, their own): each agent adds
    1/this of the noise's variance."""
    tolerance = Tolerance(corruption=settings.corruption, dropout=settings.dropout)
    return max(1, participants - tolerance.silent(participants))


class Revealed(IntEnum):
    """What a revealed share is a share of."""

    MASK_KEY = 1
    """A dropped agent's mask private key: its pairwise masks are rebuilt."""
    SELF_SEED = 2
    """An included agent's self-mask seed b_u: its self mask is removed."""
    PAIR_KEY = 3
    """The pairwise mask key s_uv itself (32 bytes, as a field element), revealed by an agent
    u for a neighbour v whose shares did not open: u holds nothing of v's secrets, and the
    server removes their pair's mask with it where v's own secrets cannot be rebuilt."""


@dataclass(frozen=True, kw_only=True)
class RoundSetup:
    """What everyone knows of a round once its mask keys are advertised."""

    round: int
    participants: tuple[int, ...]
    """The agents that advertised a mask key, in increasing order."""
    channel_keys: Mapping[int, bytes]
    """Each participant's channel public key."""
    mask_keys: Mapping[int, bytes]
    """Each participant's round mask public key: the graph is drawn from them."""
    seed_commitments: Mapping[int, bytes] = field(default_factory=dict)
    """Each participant's :func:`seed_commitment`, advertised with its mask key: a self-mask
    seed rebuilt from shares is checked against it (empty: checked by the shares alone)."""
    length: int
    """Words in each input."""
    neighbours: int
    """k of the round's plan (:func:`fedhpg.common.privacy.graph.plan_graph`); k ≥ n − 1:
    every other participant."""
    threshold: int
    """t of the round's plan: shares of an agent's secret that rebuild it."""

    @functools.cached_property
    def graph(self) -> dict[int, tuple[int, ...]]:
        """Each participant's neighbours: every other one, or its k nearest on a ring in an
        order drawn from every advertised mask key (no one can know it before they are all
        fixed)."""
        seed = graph_seed(self.round, self.mask_keys)
        return neighbour_graph(self.participants, self.neighbours, seed)

    def threshold_of(self, agent: int) -> int:
        """t of ``agent``'s neighbourhood (all of it where fewer agents advertised keys than
        the round was planned for)."""
        return min(self.threshold, len(self.graph[agent]))


def seed_commitment(round_index: int, agent: int, seed: bytes) -> bytes:
    """SHA-256 of an agent's self-mask seed, bound to the agent and round: published with its
    mask key, it hides the seed (32 random bytes) and lets anyone check a rebuilt one."""
    return hashlib.sha256(
        b"fedhpg self seed" + struct.pack("<qq", round_index, agent) + seed
    ).digest()


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
    round: int
    mask_private: bytes
    self_seed: bytes
    setup: RoundSetup | None = None
    """Known once every participant's mask key is (:meth:`SecAggAgent.share_keys`)."""
    held: dict[int, tuple[bytes, bytes]] = field(default_factory=dict)
    """Neighbour → (share of its mask key, share of its self-mask seed)."""
    masked_with: frozenset[int] = frozenset()
    unreadable: dict[int, bytes] = field(default_factory=dict)
    """Neighbour → its mask public key, of the neighbours whose sealed shares did not open."""
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

    def advertise(self, round_index: int) -> bytes:
        """Step 0: a fresh mask key pair and self-mask seed for the round; the mask public
        key to advertise."""
        state = _AgentRound(
            round=round_index, mask_private=masks.new_private_key(), self_seed=os.urandom(32)
        )
        self._round = state
        return masks.public_key(state.mask_private)

    def seed_commitment(self, round_index: int) -> bytes:
        """The commitment to the round's self-mask seed, advertised with its mask key."""
        state = self._state(round_index, shared=False)
        return seed_commitment(round_index, self.index, state.self_seed)

    def share_keys(self, setup: RoundSetup) -> KeyShares:
        """Step 1: shares of the round's mask key and self-mask seed for each neighbour of the
        graph drawn from every advertised key, each sealed for it."""
        state = self._state(setup.round, shared=False)
        if self.index not in setup.graph:
            raise SecAggError(f"agent {self.index} is not a participant of round {setup.round}")
        if state.setup is not None:
            raise SecAggError(f"round {setup.round}: agent {self.index} already shared its keys")
        if setup.mask_keys.get(self.index) != masks.public_key(state.mask_private):
            raise SecAggError(f"round {setup.round}: the server relayed another mask key as ours")
        committed = setup.seed_commitments.get(self.index)
        if setup.seed_commitments and committed != self.seed_commitment(setup.round):
            raise SecAggError(f"round {setup.round}: the server relayed another seed commitment")
        neighbours = setup.graph[self.index]
        threshold = setup.threshold_of(self.index)
        points = [share_point(v) for v in neighbours]
        key_shares = shamir.split(state.mask_private, points, threshold)
        seed_shares = shamir.split(state.self_seed, points, threshold)
        sealed = {}
        for v, key_share, seed_share in zip(neighbours, key_shares, seed_shares, strict=True):
            try:
                channel = self._channel(self.index, v, setup.channel_keys[v])
            except masks.PeerDataError:  # v cannot open anything: it holds none of our shares
                sealed[v] = os.urandom(SEALED_BYTES)
                continue
            plaintext = _associated(setup, self.index, v) + key_share + seed_share
            sealed[v] = masks.seal(channel, plaintext, _associated(setup, self.index, v))
        state.setup = setup
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
        setup = self._setup(state)
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
        masked = inputs.copy()
        fixedpoint.add(masked, masks.expand(state.self_seed, setup.length))
        for v in sorted(present):
            step = fixedpoint.add if v > self.index else fixedpoint.subtract
            try:
                step(masked, _pair_mask(state.mask_private, mask_keys[v], setup, self.index, v))
            except masks.PeerDataError:
                raise SecAggError(f"the server routed an unusable mask key of agent {v}") from None
        held, unreadable = {}, {}
        for v in sorted(present):
            opened = self._open(setup, v, sealed[v])
            if opened is None:
                unreadable[v] = mask_keys[v]
            else:
                held[v] = opened
        state.held, state.unreadable = held, unreadable
        state.masked_with = frozenset(present)
        return masked

    def unreadable(self, round_index: int) -> frozenset[int]:
        """The neighbours whose sealed shares did not open in step 2 (their drop-out as far
        as this agent's shares go: it holds none of theirs)."""
        return frozenset(self._state(round_index).unreadable)

    def _open(self, setup: RoundSetup, v: int, sealed: bytes) -> tuple[bytes, bytes] | None:
        """The two shares agent ``v`` sealed for this agent; None if they do not open (altered,
        replayed from another round or pair, or not a share at all)."""
        try:
            channel = self._channel(v, self.index, setup.channel_keys[v])
            plaintext = masks.open_sealed(channel, sealed, _associated(setup, v, self.index))
        except masks.PeerDataError:
            return None
        header, rest = plaintext[: SHARE_PLAINTEXT.size], plaintext[SHARE_PLAINTEXT.size :]
        if header != _associated(setup, v, self.index) or len(rest) != 2 * shamir.SHARE_BYTES:
            return None
        return rest[: shamir.SHARE_BYTES], rest[shamir.SHARE_BYTES :]

    def reveal(
        self, round_index: int, dropped: Collection[int], included: Collection[int]
    ) -> dict[int, tuple[Revealed, bytes]]:
        """Step 3: for each neighbour it masked with, the share of its mask key (it dropped)
        or of its self-mask seed (its input is in the sum); never both, never twice. For a
        neighbour whose shares did not open, their pair's mask key instead."""
        state = self._state(round_index)
        dropped, included = set(dropped), set(included)
        if state.revealed:
            raise SecAggError(f"round {round_index}: agent {self.index} already revealed")
        if dropped & included or self.index not in included:
            raise SecAggError("an unmasking request must name disjoint sets, this agent included")
        if not (dropped | included) >= state.masked_with:
            raise SecAggError("an unmasking request must account for every neighbour masked with")
        setup = self._setup(state)
        threshold = setup.threshold_of(self.index)
        if len(state.masked_with & included) + 1 < threshold:  # + 1: itself
            raise SecAggError(
                f"round {round_index}: fewer than {threshold} of agent {self.index}'s "
                "neighbourhood sent inputs"
            )
        state.revealed = True
        answer: dict[int, tuple[Revealed, bytes]] = {}
        for v in sorted(state.masked_with):
            if v in state.unreadable:
                pair_key = _pair_key(state.mask_private, state.unreadable[v], setup, self.index, v)
                answer[v] = (Revealed.PAIR_KEY, pair_key.rjust(shamir.SHARE_BYTES, b"\0"))
                continue
            key_share, seed_share = state.held[v]
            if v in dropped:
                answer[v] = (Revealed.MASK_KEY, key_share)
            else:
                answer[v] = (Revealed.SELF_SEED, seed_share)
        return answer

    def _state(self, round_index: int, *, shared: bool = True) -> _AgentRound:
        """The round in progress (``shared``: with its shares sent, so its setup known)."""
        state = self._round
        if state is None or state.round != round_index:
            raise SecAggError(f"agent {self.index} has no keys for round {round_index}")
        if shared and state.setup is None:
            raise SecAggError(f"round {round_index}: agent {self.index} shared no keys")
        return state

    def _setup(self, state: _AgentRound) -> RoundSetup:
        assert state.setup is not None  # _state(shared=True) checked it
        return state.setup


def _pair_key(private: bytes, peer_public: bytes, setup: RoundSetup, u: int, v: int) -> bytes:
    """s_uv: the 32-byte key both agents of a pair agree from their mask keys."""
    return masks.agree(private, peer_public, masks.mask_purpose(setup.round, u, v))


def _pair_mask(private: bytes, peer_public: bytes, setup: RoundSetup, u: int, v: int) -> np.ndarray:
    """PRG(s_uv): the words both agents of a pair derive from their mask keys."""
    return masks.expand(_pair_key(private, peer_public, setup, u, v), setup.length)


class _Blame(Exception):
    """Holders whose revealed shares were found wrong: the sum is rebuilt without them."""

    def __init__(self, holders: Mapping[int, str]) -> None:
        super().__init__(dict(holders))
        self.holders = dict(holders)


class SecAggRound:
    """The server's side of one aggregation: it routes, collects and unmasks, never sees an
    input alone.

    Every value an agent sends is checked before it is kept (:meth:`add_keys`,
    :meth:`add_masked`, :meth:`add_reveal` raise SecAggError: the caller counts that agent as
    dropped out at that step), and every secret rebuilt is checked (:func:`shamir.rebuild`: the
    shares beyond the threshold must agree, a mask key must match the public key its owner
    advertised): a holder whose shares are wrong is left out of the unmasking."""

    def __init__(self, setup: RoundSetup) -> None:
        self.setup = setup
        self.keys: dict[int, KeyShares] = {}
        """U1: who shared keys."""
        self.inputs: dict[int, np.ndarray] = {}
        """U2: the masked inputs that arrived."""
        self.reveals: dict[int, dict[int, tuple[Revealed, bytes]]] = {}
        """U3: who answered the unmasking request."""
        self.summed: list[int] = []
        """After :meth:`total`: whose inputs the sum holds (U2, less any agent whose self mask
        could not be rebuilt: see :attr:`left_out`)."""
        self.left_out: dict[int, str] = {}
        """After :meth:`total`: agents of U2 whose inputs the sum does not hold, and why."""
        self.blamed: dict[int, str] = {}
        """After :meth:`total`: agents whose revealed shares were wrong (left out of the
        unmasking; their own inputs stay in the sum), and why."""

    def add_keys(self, agent: int, shares: KeyShares) -> None:
        graph = self.setup.graph
        if agent not in graph:
            raise SecAggError(f"agent {agent} is not a participant of round {self.setup.round}")
        if agent in self.keys:
            raise SecAggError(f"agent {agent} already shared keys")
        if set(shares.sealed) != set(graph[agent]):
            raise SecAggError(f"agent {agent}'s key shares do not match its neighbours")
        if any(len(c) != SEALED_BYTES for c in shares.sealed.values()):
            raise SecAggError(f"agent {agent}'s sealed shares are not {SEALED_BYTES} bytes")
        if not masks.usable_public_key(shares.mask_key):
            raise SecAggError(f"agent {agent}'s mask key agrees on no secret")
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
        if agent in self.inputs:
            raise SecAggError(f"agent {agent} already sent its input")
        if masked.shape != (self.setup.length,) or masked.dtype != np.uint64:
            raise SecAggError(f"agent {agent}'s input is not {self.setup.length} uint64 words")
        self.inputs[agent] = masked.copy()

    def unmask_request(self) -> tuple[list[int], list[int]]:
        """(dropped: shared keys but sent no input, included: sent an input)."""
        return sorted(set(self.keys) - set(self.inputs)), sorted(self.inputs)

    def add_reveal(self, agent: int, shares: Mapping[int, tuple[Revealed, bytes]]) -> None:
        """``agent``'s answer to the unmasking request: for each neighbour it masked with, a
        share of its mask key (it dropped) or of its self seed (included), or their pair's
        mask key (its shares did not open)."""
        if agent not in self.inputs:
            raise SecAggError(f"agent {agent} revealed shares without an input in the sum")
        if agent in self.reveals:
            raise SecAggError(f"agent {agent} already revealed its shares")
        masked_with = {v for v in self.setup.graph[agent] if v in self.keys}
        for owner, (kind, share) in shares.items():
            if owner not in masked_with:
                raise SecAggError(f"agent {agent} revealed a secret of {owner}, not a neighbour")
            wanted = Revealed.SELF_SEED if owner in self.inputs else Revealed.MASK_KEY
            if kind not in (wanted, Revealed.PAIR_KEY):
                raise SecAggError(
                    f"agent {agent} revealed a share of {owner}'s {_name(kind)}, not of its "
                    f"{_name(wanted)}"
                )
            limit = 1 << (8 * masks.KEY_BYTES) if kind is Revealed.PAIR_KEY else shamir.PRIME
            if len(share) != shamir.SHARE_BYTES or int.from_bytes(share, "big") >= limit:
                raise SecAggError(f"agent {agent}'s share of {owner}'s {_name(kind)} is no share")
        self.reveals[agent] = dict(shares)

    def total(self, fewest: int = 1) -> np.ndarray:
        """Σ x_u over the agents of :attr:`summed`, modulo 2⁶⁴; SecAggError when some secret
        the sum needs has fewer than t right shares among the answers, or when the sum would
        hold fewer than ``fewest`` inputs (it is then never computed)."""
        dropped, included = self.unmask_request()
        if not included:
            raise SecAggError(f"round {self.setup.round}: no masked input arrived")
        blamed: dict[int, str] = {}
        for _ in range(len(self.reveals) + 1):  # each pass leaves out one holder at least
            try:
                words, summed, left_out = self._unmasked(dropped, included, set(blamed), fewest)
            except _Blame as blame:
                blamed.update(blame.holders)
                continue
            self.summed, self.left_out, self.blamed = summed, left_out, blamed
            return words
        raise SecAggError(f"round {self.setup.round}: the revealed shares do not interpolate")

    def _key_check(self, owner: int) -> Callable[[bytes], bool]:
        """Whether a rebuilt mask private key is ``owner``'s advertised one."""
        advertised = self.keys[owner].mask_key
        return lambda key: masks.public_key(key) == advertised

    def _seed_check(self, owner: int) -> Callable[[bytes], bool] | None:
        """Whether a rebuilt seed is ``owner``'s committed one (None: no commitment)."""
        committed = self.setup.seed_commitments.get(owner)
        if committed is None:
            return None
        return lambda seed: seed_commitment(self.setup.round, owner, seed) == committed

    def _unmasked(
        self, dropped: list[int], included: list[int], excluded: set[int], fewest: int
    ) -> tuple[np.ndarray, list[int], dict[int, str]]:
        """One unmasking without the shares of ``excluded`` holders; _Blame when shares turn
        out wrong (their holders are named), SecAggError when a needed secret cannot be
        rebuilt."""
        setup = self.setup
        collected: dict[tuple[int, Revealed], dict[int, bytes]] = {}
        pair_keys: dict[tuple[int, int], bytes] = {}
        for holder, shares in self.reveals.items():
            if holder in excluded:
                continue
            for owner, (kind, share) in shares.items():
                if kind is Revealed.PAIR_KEY:
                    pair_keys[holder, owner] = share[-masks.KEY_BYTES :]
                else:
                    collected.setdefault((owner, kind), {})[share_point(holder)] = share
        rebuild = _Rebuild(setup, collected)
        seeds = {u: rebuild.secret(u, Revealed.SELF_SEED, self._seed_check(u)) for u in included}
        rebuild.settle()
        summed = [u for u in included if seeds[u] is not None]
        missing = [u for u in included if seeds[u] is None]
        for u in missing:  # out of the sum if every summed partner can undo their pair mask
            partners = [w for w in setup.graph[u] if w in summed]
            if not summed or any((w, u) not in pair_keys for w in partners):
                raise SecAggError(rebuild.shortfall(u, Revealed.SELF_SEED))
        if len(summed) < fewest:
            raise SecAggError(
                f"round {setup.round}: {len(summed)} inputs could be unmasked, fewer than {fewest}"
            )
        total = np.zeros(setup.length, dtype=np.uint64)
        for u in summed:
            fixedpoint.add(total, self.inputs[u])
            fixedpoint.subtract(total, masks.expand(seeds[u] or b"", setup.length))
        for v in [*dropped, *missing]:
            partners = [u for u in setup.graph[v] if u in summed]
            private = None
            if v in dropped and any((u, v) not in pair_keys for u in partners):
                private = rebuild.secret(v, Revealed.MASK_KEY, self._key_check(v))
                rebuild.settle()
                if private is None:
                    raise SecAggError(rebuild.shortfall(v, Revealed.MASK_KEY))
            for u in partners:
                # u added +PRG(s_uv) for v > u, −PRG(s_uv) for v < u: take it back out
                step = fixedpoint.subtract if v > u else fixedpoint.add
                if private is not None:
                    step(total, _pair_mask(private, self.keys[u].mask_key, setup, v, u))
                else:
                    step(total, masks.expand(pair_keys[u, v], setup.length))
        left_out = {
            u: "its self-mask seed could not be rebuilt (its shares did not open for its "
            "neighbours)"
            for u in missing
        }
        return total, summed, left_out


class _Rebuild:
    """The secrets of one unmasking, each from its shares (checked), and what went wrong."""

    def __init__(
        self, setup: RoundSetup, collected: Mapping[tuple[int, Revealed], dict[int, bytes]]
    ) -> None:
        self.setup = setup
        self.collected = collected
        self.wrong: dict[int, str] = {}
        """Holders whose shares disagree with the others'."""
        self.suspects: list[tuple[frozenset[int], str]] = []
        """Share sets that do not interpolate, no one share to blame: (holders, what)."""

    def secret(
        self, owner: int, kind: Revealed, accept: Callable[[bytes], bool] | None = None
    ) -> bytes | None:
        """``owner``'s secret of ``kind``; None without enough right shares. ``accept``: a
        check of the secret itself (a mask key against its public key, a seed against its
        commitment)."""
        shares = self.collected.get((owner, kind), {})
        threshold = self.setup.threshold_of(owner)
        if len(shares) < threshold:
            return None
        what = f"agent {owner}'s {_name(kind)}"

        try:
            try:
                secret, wrong = shamir.rebuild(shares, threshold, accept)
            except shamir.Inconsistent:
                if kind is not Revealed.SELF_SEED or accept is None:
                    raise
                # no t of them match the seed's commitment: the owner may have advertised a
                # wrong one, so the shares alone decide, as without a commitment
                secret, wrong = shamir.rebuild(shares, threshold)
        except shamir.Inconsistent as error:
            self.suspects.append((frozenset(x - 1 for x in error.suspects), what))
            return None
        for x in wrong:
            self.wrong[x - 1] = f"its share of {what} does not interpolate with the others"
        return secret

    def settle(self) -> None:
        """_Blame for the holders found wrong, or the one holder every inconsistent share set
        has in common; SecAggError when shares disagree and no one holder explains it."""
        if self.wrong:
            raise _Blame(self.wrong)
        if not self.suspects:
            return
        common = frozenset.intersection(*(holders for holders, _ in self.suspects))
        if len(common) == 1:
            raise _Blame({h: "its shares do not interpolate with the others" for h in common})
        raise SecAggError(
            f"round {self.setup.round}: the shares of {self.suspects[0][1]} do not "
            "interpolate to one secret"
        )

    def shortfall(self, owner: int, kind: Revealed) -> str:
        count = len(self.collected.get((owner, kind), {}))
        return (
            f"round {self.setup.round}: {count} share(s) of agent {owner}'s {_name(kind)}, "
            f"fewer than the threshold {self.setup.threshold_of(owner)}"
        )


def _name(kind: Revealed) -> str:
    return kind.name.lower().replace("_", " ")
