"""A secure round against one registered participant that breaks the protocol: whatever it
sends (malformed keys, sealed shares, masked inputs or revealed shares; replays of its own
earlier messages), the server and the honest agents go on, the rogue drops out (or its wrong
shares are left out), and the honest agents' inputs are aggregated exactly. A round that
cannot be aggregated is skipped and recorded, never the end of the run.

The rounds run the server's exchange against the agents' own sides through the codec
(tests/secure_peers.py), without sockets."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from functools import cache

import numpy as np
import pytest
from secure_peers import HonestSide, Reply, RogueSide, honest_mean, secure_round

from fedhpg.common.config import RunConfig
from fedhpg.common.privacy.secagg import SEALED_BYTES
from fedhpg.common.runtime.cli import compose
from fedhpg.common.types import UpdateColumns
from fedhpg.common.wire.protocol import (
    KeyShares,
    MaskedUpdate,
    MaskRequest,
    Message,
    Train,
    Unmasking,
    UnmaskRequest,
)

K = 5
ROGUE = 2
HONEST = [k for k in range(K) if k != ROGUE]
TOLERANCE = 1e-9
"""The fixed point's resolution at K = 5 and range 10⁴ is ~10⁻¹⁴ a coordinate."""


@cache
def run_of(mode: str = "secagg", k: int = K) -> RunConfig:
    return compose(
        [f"privacy={mode}", "agents=homogeneous10", f"agents.num_agents={k}"], report=False
    )


def sides_with(
    script: Callable[[Message, list[Reply]], list[Reply]], run: RunConfig | None = None
) -> dict[int, HonestSide]:
    run = run or run_of()
    sides = {k: HonestSide(run, k) for k in range(K)}
    sides[ROGUE] = RogueSide(run, ROGUE, script)
    return sides


def tamper(kind: type, **fields: Callable[[object], object]) -> Callable:
    """A script: the rogue's answers of type ``kind`` with ``fields`` replaced by a function of
    the honest message."""

    def script(request: Message, honest: list[Reply]) -> list[Reply]:
        out: list[Reply] = []
        for message in honest:
            if isinstance(message, kind):
                changes = {name: change(message) for name, change in fields.items()}
                message = dataclasses.replace(message, **changes)  # type: ignore[type-var]
            out.append(message)
        return out

    return script


def assert_honest_mean(answers, included: list[int]) -> None:
    secure = answers.secure
    assert secure is not None and secure.failed is None, secure
    assert secure.inputs == len(included)
    assert sorted(u.agent_index for u in answers.updates) == included
    assert secure.total[-2] == pytest.approx(len(included), abs=TOLERANCE)
    np.testing.assert_allclose(
        secure.total[:-2] / secure.total[-2], honest_mean(included), rtol=0, atol=TOLERANCE
    )


# --- a malformed row is its agent's drop-out, never the server's crash ---------------------------

MALFORMED = {
    "key shares: too few recipients rows": tamper(KeyShares, recipients=lambda m: m.recipients[:0]),
    "key shares: 1-D sealed": tamper(KeyShares, sealed=lambda m: m.sealed.reshape(-1)),
    "key shares: a 31-byte mask key": tamper(KeyShares, mask_keys=lambda m: m.mask_keys[:, :31]),
    "key shares: a recipient twice": tamper(
        KeyShares, recipients=lambda m: np.full_like(m.recipients, m.recipients[0, 0])
    ),
    "key shares: a recipient out of range": tamper(
        KeyShares, recipients=lambda m: m.recipients - 7
    ),
    "masked update: uint8 words": tamper(MaskedUpdate, masked=lambda m: m.masked.view(np.uint8)),
    "masked update: short stats": tamper(MaskedUpdate, stats=lambda m: UpdateColumns.of([])),
    "masked update: a word short": tamper(MaskedUpdate, masked=lambda m: m.masked[:, :-1]),
}


@pytest.mark.parametrize("script", MALFORMED.values(), ids=MALFORMED.keys())
def test_a_malformed_key_share_or_input_drops_its_agent_only(script: Callable) -> None:
    answers = secure_round(run_of(), sides_with(script))
    assert_honest_mean(answers, HONEST)
    assert list(answers.failures) == [f"agent-{ROGUE}"]
    assert "refused" in answers.failures[f"agent-{ROGUE}"].reason


def _garbage_shares(m: Unmasking) -> np.ndarray:
    shares = np.random.default_rng(0).integers(0, 256, m.shares.shape, dtype=np.uint8)
    shares[..., :2] = 0  # a field element below p = 2^521 - 1
    return shares


REVEALS = {
    "unmasking: mismatched widths": tamper(Unmasking, kinds=lambda m: m.kinds[:, :-1]),
    "unmasking: shares that do not interpolate": tamper(Unmasking, shares=_garbage_shares),
    "unmasking: a kind that names no secret": tamper(
        Unmasking, kinds=lambda m: np.full_like(m.kinds, 7)
    ),
    "unmasking: an owner twice": tamper(
        Unmasking, owners=lambda m: np.full_like(m.owners, m.owners[0, 0])
    ),
}


@pytest.mark.parametrize("script", REVEALS.values(), ids=REVEALS.keys())
def test_wrong_revealed_shares_are_left_out_and_the_sum_is_exact(script: Callable) -> None:
    # the rogue's masked input was fine: it stays in the sum, its wrong shares do not
    answers = secure_round(run_of(), sides_with(script))
    assert_honest_mean(answers, list(range(K)))


def test_a_secret_shared_with_one_wrong_share_is_rebuilt_without_it() -> None:
    # agent 6 drops after sharing keys: its mask key is rebuilt from the others' shares, of
    # which the rogue's are wrong (t = 4 of 6 neighbours: 5 honest holders remain)
    def silent_after_keys(request: Message, honest: list[Reply]) -> list[Reply]:
        return honest if isinstance(request, Train) else []

    run = run_of(k=7)
    sides = {k: HonestSide(run, k) for k in range(7)}
    sides[ROGUE] = RogueSide(run, ROGUE, tamper(Unmasking, shares=_garbage_shares))
    sides[6] = RogueSide(run, 6, silent_after_keys)
    answers = secure_round(run, sides)
    assert_honest_mean(answers, list(range(6)))


# --- a peer's crypto failure is that peer's drop-out, never an honest agent's exit --------------


def _random_sealed(m: KeyShares) -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, m.sealed.shape, dtype=np.uint8)


def test_garbage_sealed_shares_drop_their_sender_only() -> None:
    answers = secure_round(run_of(), sides_with(tamper(KeyShares, sealed=_random_sealed)))
    assert_honest_mean(answers, HONEST)
    assert "left out of the sum" in answers.failures[f"agent-{ROGUE}"].reason


def test_replayed_sealed_shares_drop_their_sender_only() -> None:
    kept: dict[str, np.ndarray] = {}

    def replay(request: Message, honest: list[Reply]) -> list[Reply]:
        out = []
        for message in honest:
            if isinstance(message, KeyShares):
                if "sealed" in kept:  # last round's boxes, as they were sent
                    message = dataclasses.replace(message, sealed=kept["sealed"])
                kept.setdefault("sealed", message.sealed)
            out.append(message)
        return out

    sides = sides_with(replay)
    assert_honest_mean(secure_round(run_of(), sides, round_index=1), list(range(K)))
    assert_honest_mean(secure_round(run_of(), sides, round_index=2), HONEST)


def test_an_all_zero_mask_key_drops_its_sender_only() -> None:
    script = tamper(KeyShares, mask_keys=lambda m: np.zeros_like(m.mask_keys))
    answers = secure_round(run_of(), sides_with(script))
    assert_honest_mean(answers, HONEST)
    assert "agrees on no secret" in answers.failures[f"agent-{ROGUE}"].reason


def test_an_unusable_channel_key_leaves_its_agent_out() -> None:
    sides = {k: HonestSide(run_of(), k) for k in range(K)}
    keys = {k: s.channel_key for k, s in sides.items()}
    keys[ROGUE] = bytes(32)
    answers = secure_round(run_of(), sides, keys=keys)
    assert_honest_mean(answers, HONEST)


# --- the agents read the server's requests with every field checked ------------------------------


def _honest_requests() -> tuple[dict[int, HonestSide], list[Message]]:
    """The requests agent 0 gets in a clean round (recorded from the server's side)."""
    seen: list[Message] = []

    def record(request: Message, honest: list[Reply]) -> list[Reply]:
        seen.append(request)
        return honest

    run = run_of()
    sides = {k: HonestSide(run, k) for k in range(K)}
    sides[0] = RogueSide(run, 0, record)
    secure_round(run, sides)
    return sides, seen


BAD_REQUESTS: dict[str, Callable[[Message], Message]] = {
    "train: participants twice": lambda r: dataclasses.replace(
        r, participants=[0, 0, 1, 2, 3], channel_keys=r.channel_keys
    ),
    "train: 31-byte channel keys": lambda r: dataclasses.replace(
        r, channel_keys=r.channel_keys[:, :31]
    ),
    "train: a key row short": lambda r: dataclasses.replace(r, channel_keys=r.channel_keys[:-1]),
    "mask request: a sender twice": lambda r: dataclasses.replace(
        r, senders=np.full_like(r.senders, r.senders[0, 0])
    ),
    "mask request: 1-D sealed": lambda r: dataclasses.replace(r, sealed=r.sealed.reshape(-1)),
    "mask request: int32 senders": lambda r: dataclasses.replace(
        r, senders=r.senders.astype(np.int32)
    ),
    "mask request: zero mask keys": lambda r: dataclasses.replace(
        r, mask_keys=np.zeros_like(r.mask_keys)
    ),
    "mask request: a sealed box short": lambda r: dataclasses.replace(
        r, sealed=r.sealed[:, :, : SEALED_BYTES - 1]
    ),
    "unmask request: dropped and included overlap": lambda r: dataclasses.replace(
        r, dropped=list(r.included)
    ),
}


@pytest.mark.parametrize("change", BAD_REQUESTS.values(), ids=BAD_REQUESTS.keys())
def test_an_agent_refuses_a_malformed_request_without_raising(change: Callable) -> None:
    sides, requests = _honest_requests()
    kind = {"train": Train, "mask": MaskRequest, "unmask": UnmaskRequest}
    name = next(n for n in BAD_REQUESTS if BAD_REQUESTS[n] is change)
    wanted = kind[name.split(" request")[0].split(":")[0]]
    index = next(i for i, r in enumerate(requests) if type(r) is wanted)
    side = sides[0]
    for request in requests[:index]:  # the round's earlier steps, as they were
        HonestSide.answer(side, request)
    assert HonestSide.answer(side, change(requests[index])) == []
