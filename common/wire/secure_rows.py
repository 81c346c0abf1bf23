"""The secure rounds' wire messages read row by row, every field checked before any is used.

A secure round's messages (:mod:`fedhpg.common.wire.protocol`: ``MaskKeys``, ``KeyShares``,
``MaskedUpdate``, ``Unmasking`` from agents; ``Train``'s participants, ``ShareRequest``,
``MaskRequest`` and ``UnmaskRequest`` from the server) carry arrays the codec checked for
their dtype's kind and size only. Each reader here returns the row's values as the protocol
(:mod:`fedhpg.common.privacy.secagg`) takes them, or raises :class:`RowError` saying what is
wrong: shapes and dtypes, key and share sizes, indices out of range, a neighbour named twice.
The protocol then checks what needs the round (who is whose neighbour, who dropped out). A row
that cannot be read is its agent's drop-out at that step, never a failure of the reader.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from fedhpg.common.privacy import masks, shamir
from fedhpg.common.privacy.secagg import SEALED_BYTES, KeyShares, Revealed
from fedhpg.common.privacy.signing import SIGNATURE_BYTES
from fedhpg.common.records.types import UpdateStats
from fedhpg.common.wire import protocol

COMMITMENT_BYTES = 32
"""A seed commitment: SHA-256 (:func:`fedhpg.common.privacy.secagg.seed_commitment`)."""
UNUSED = -1
"""An index slot that names no agent (rows are padded to the widest)."""


class RowError(ValueError):
    """A row of a secure round's message that cannot be used: its agent drops out."""


def mask_keys(message: protocol.MaskKeys, row: int) -> tuple[bytes, bytes, bytes]:
    """Row ``row`` of an agent's ``MaskKeys``: its round mask public key, its seed commitment
    and its signature."""
    rows = len(message.agents)
    keys = _array(message.mask_keys, "mask_keys", np.uint8, rows, (masks.KEY_BYTES,))
    commitments = _array(
        message.seed_commitments, "seed_commitments", np.uint8, rows, (COMMITMENT_BYTES,)
    )
    signatures = _array(message.signatures, "signatures", np.uint8, rows, (SIGNATURE_BYTES,))
    mask_key = bytes(keys[row])
    if not masks.usable_public_key(mask_key):
        raise RowError("the mask key agrees on no secret (a low-order point)")
    return mask_key, bytes(commitments[row]), bytes(signatures[row])


def share_request(
    request: protocol.ShareRequest,
) -> tuple[dict[int, bytes], dict[int, bytes], dict[int, bytes]]:
    """A ``ShareRequest``'s advertised mask keys, seed commitments and signatures, by
    participant (strictly increasing, each key usable, the agents asked among them)."""
    participants = list(request.participants)
    if any(b <= a for a, b in itertools.pairwise(participants)):
        raise RowError("the participants are not strictly increasing")
    count = len(participants)
    keys = _array(request.mask_keys, "mask_keys", np.uint8, count, (masks.KEY_BYTES,))
    commitments = _array(
        request.seed_commitments, "seed_commitments", np.uint8, count, (COMMITMENT_BYTES,)
    )
    signatures = _array(request.signatures, "signatures", np.uint8, count, (SIGNATURE_BYTES,))
    if not set(request.agents) <= set(participants):
        raise RowError("the request names agents that advertised no mask key")
    advertised = {k: bytes(row) for k, row in zip(participants, keys, strict=True)}
    if not all(masks.usable_public_key(key) for key in advertised.values()):
        raise RowError("a mask key agrees on no secret (a low-order point)")
    return (
        advertised,
        {k: bytes(row) for k, row in zip(participants, commitments, strict=True)},
        {k: bytes(row) for k, row in zip(participants, signatures, strict=True)},
    )


def key_shares(message: protocol.KeyShares, row: int) -> KeyShares:
    """Row ``row`` of an agent's ``KeyShares``: its mask public key and a sealed box for each
    recipient named."""
    rows = len(message.agents)
    mask_keys = _array(message.mask_keys, "mask_keys", np.uint8, rows, (masks.KEY_BYTES,))
    recipients = _array(message.recipients, "recipients", np.int64, rows, (None,))
    sealed = _array(message.sealed, "sealed", np.uint8, rows, (recipients.shape[1], SEALED_BYTES))
    mask_key = bytes(mask_keys[row])
    if not masks.usable_public_key(mask_key):
        raise RowError("the mask key agrees on no secret (a low-order point)")
    slots = _slots(recipients[row], "recipients")
    return KeyShares(mask_key=mask_key, sealed={v: bytes(sealed[row, j]) for j, v in slots})


def masked_update(
    message: protocol.MaskedUpdate, row: int, length: int
) -> tuple[np.ndarray, UpdateStats]:
    """Row ``row`` of an agent's ``MaskedUpdate``: its masked input (``length`` uint64 words)
    and its statistics."""
    rows = len(message.agents)
    masked = _array(message.masked, "masked", np.int64, rows, (length,))
    if len(message.stats) != rows:
        raise RowError(f"stats has {len(message.stats)} rows for {rows} agents")
    stats = message.stats[row]
    problems = stats.problems()
    if problems:
        raise RowError("stats: " + "; ".join(problems))
    return np.ascontiguousarray(masked[row]).view(np.uint64).copy(), stats


def unmasking(message: protocol.Unmasking, row: int) -> dict[int, tuple[Revealed, bytes]]:
    """Row ``row`` of an agent's ``Unmasking``: owner → (what it reveals, the 66 bytes)."""
    rows = len(message.agents)
    owners = _array(message.owners, "owners", np.int64, rows, (None,))
    kinds = _array(message.kinds, "kinds", np.uint8, rows, (owners.shape[1],))
    shares = _array(message.shares, "shares", np.uint8, rows, (owners.shape[1], shamir.SHARE_BYTES))
    revealed: dict[int, tuple[Revealed, bytes]] = {}
    for j, owner in _slots(owners[row], "owners"):
        kind = int(kinds[row, j])
        if kind not in Revealed._value2member_map_:
            raise RowError(f"owner {owner}'s slot is of kind {kind}, which names no secret")
        revealed[owner] = (Revealed(kind), bytes(shares[row, j]))
    return revealed


def mask_request(
    request: protocol.MaskRequest, row: int
) -> tuple[dict[int, bytes], dict[int, bytes]]:
    """Row ``row`` of a ``MaskRequest``: the neighbours' mask keys and the boxes they sealed
    for this row's agent."""
    rows = len(request.agents)
    senders = _array(request.senders, "senders", np.int64, rows, (None,))
    width = senders.shape[1]
    mask_keys = _array(request.mask_keys, "mask_keys", np.uint8, rows, (width, masks.KEY_BYTES))
    sealed = _array(request.sealed, "sealed", np.uint8, rows, (width, SEALED_BYTES))
    slots = _slots(senders[row], "senders")
    return (
        {v: bytes(mask_keys[row, j]) for j, v in slots},
        {v: bytes(sealed[row, j]) for j, v in slots},
    )


def train_participants(request: protocol.Train) -> dict[int, bytes]:
    """A private ``Train``'s participants (strictly increasing) and their channel keys, one
    32-byte row each."""
    participants = list(request.participants)
    if any(b <= a for a, b in itertools.pairwise(participants)):
        raise RowError("the participants are not strictly increasing")
    keys = _array(
        request.channel_keys, "channel_keys", np.uint8, len(participants), (masks.KEY_BYTES,)
    )
    if not set(request.agents) <= set(participants):
        raise RowError("the request names agents that are not participants")
    return {k: bytes(row) for k, row in zip(participants, keys, strict=True)}


def _array(
    value: object,
    name: str,
    dtype: type[np.generic],
    rows: int,
    trailing: Sequence[int | None],
) -> np.ndarray:
    """``value`` as an array of ``dtype`` shaped [rows, *trailing] (None: any size)."""
    if not isinstance(value, np.ndarray) or value.dtype != np.dtype(dtype):
        kind = value.dtype if isinstance(value, np.ndarray) else type(value).__name__
        raise RowError(f"{name} is {kind}, not {np.dtype(dtype)}")
    shape = value.shape
    fits = len(shape) == 1 + len(trailing) and shape[0] == rows
    if not fits or any(w is not None and g != w for g, w in zip(shape[1:], trailing, strict=True)):
        wanted = ", ".join("k" if d is None else str(d) for d in (rows, *trailing))
        raise RowError(f"{name} is shaped {list(shape)}, not [{wanted}]")
    return value


def _slots(indices: np.ndarray, name: str) -> list[tuple[int, int]]:
    """(slot, agent) of a row's used slots: agents named once each, unused slots −1."""
    used = [(j, int(v)) for j, v in enumerate(indices) if v != UNUSED]
    agents = [v for _, v in used]
    if any(v < 0 for v in agents):
        raise RowError(f"{name} holds an index below {UNUSED}")
    if len(set(agents)) != len(agents):
        raise RowError(f"{name} names an agent twice")
    return used
