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
import torch
from secure_peers import (
    HonestSide,
    Reply,
    RogueSide,
    SecurePool,
    honest_mean,
    secure_round,
    step_of,
)

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy import fixedpoint
from fedhpg.common.privacy.secagg import SEALED_BYTES, noise_shares
from fedhpg.common.records.types import UpdateColumns
from fedhpg.common.runtime.cli import compose
from fedhpg.common.wire.protocol import (
    KeyShares,
    MaskedUpdate,
    MaskKeys,
    MaskRequest,
    Message,
    ShareRequest,
    Train,
    Unmasking,
    UnmaskRequest,
)
from fedhpg.server.coordinator import Coordinator, RoundRecord
from fedhpg.server.pools import FederationError
from fedhpg.server.privacy import PrivateRounds
from fedhpg.server.strategies import make_strategy

K = 5
ROGUE = 4
HONEST = [k for k in range(K) if k != ROGUE]
NUM_PARAMS = 6
"""θ̃'s size in these rounds (the strategies and the protocol take any)."""
TOLERANCE = 1e-9
"""The fixed point's resolution at K = 5 and range 10⁴ is ~10⁻¹⁴ a coordinate."""


@cache
def run_of(mode: str = "secagg", k: int = K) -> RunConfig:
    return compose(
        [f"privacy={mode}", "agents=homogeneous10", f"agents.num_agents={k}"], report=False
    )


def sides_with(
    script: Callable[[Message, list[Reply]], list[Reply]],
    run: RunConfig | None = None,
    rogue: int = ROGUE,
) -> dict[int, HonestSide]:
    run = run or run_of()
    sides = {k: HonestSide(run, k) for k in range(K)}
    sides[rogue] = RogueSide(run, rogue, script)
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
    assert answers.result.agents == included
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


@pytest.mark.parametrize("rogue", [0, 2, 4])  # its shares first, among, or after the rest
@pytest.mark.parametrize("script", REVEALS.values(), ids=REVEALS.keys())
def test_wrong_revealed_shares_are_left_out_and_the_sum_is_exact(
    script: Callable, rogue: int
) -> None:
    # the rogue's masked input was fine: it stays in the sum, its wrong shares do not
    answers = secure_round(run_of(), sides_with(script, rogue=rogue))
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


def test_one_wrong_share_among_t_plus_one_is_outvoted_by_the_seed_commitment() -> None:
    # five agents: each secret has t + 1 = 4 shares; the rogue flips one byte of one share. The
    # shares alone cannot tell which of the four is wrong; the seed's advertised commitment
    # can: the right secret is the one some t of them rebuild that matches it, and every input
    # is summed exactly
    def one_flip(m: Unmasking) -> np.ndarray:
        shares = m.shares.copy()
        shares[0, 0, -1] ^= 1
        return shares

    answers = secure_round(run_of(), sides_with(tamper(Unmasking, shares=one_flip)))
    assert_honest_mean(answers, list(range(5)))  # the rogue's own input was honest


def test_without_commitments_one_wrong_share_among_t_plus_one_skips_the_round() -> None:
    """The control (a round set up without seed commitments, as the protocol's own tests
    do): the disagreement is found, but any of the four may be the wrong one, so the round
    has no sum, never a wrong one."""
    from fedhpg.common.privacy import secagg

    agents = {k: secagg.SecAggAgent(k) for k in range(5)}
    setup = secagg.RoundSetup(
        round=1,
        participants=tuple(range(5)),
        channel_keys={k: a.channel_public for k, a in agents.items()},
        mask_keys={k: a.advertise(1) for k, a in agents.items()},
        length=3,
        neighbours=4,
        threshold=3,
    )
    server = secagg.SecAggRound(setup)
    for k, agent in agents.items():
        server.add_keys(k, agent.share_keys(setup))
    for k, agent in agents.items():
        server.add_masked(k, agent.mask(1, np.zeros(3, np.uint64), *server.routed(k)))
    dropped, included = server.unmask_request()
    for k in included:
        revealed = agents[k].reveal(1, dropped, included)
        if k == 0:
            owner = next(iter(revealed))
            kind, share = revealed[owner]
            revealed[owner] = (kind, share[:-1] + bytes([share[-1] ^ 1]))
        server.add_reveal(k, revealed)
    with pytest.raises(secagg.SecAggError, match="do not interpolate"):
        server.total()


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


# --- the sum's public weight column and step are checked before θ̃ is adopted -------------------


class ForgedInput(HonestSide):
    """Agent k whose contribution is ``value`` in every coordinate of the update and
    ``weight`` in the weight column: any words it likes, masked as the protocol asks."""

    def __init__(self, run: RunConfig, k: int, weight: float, value: float) -> None:
        super().__init__(run, k)
        self.weight, self.value = weight, value

    def answer(self, request: Message) -> list[Reply]:
        answers = super().answer(request)
        if isinstance(request, Train):
            row = np.full(6 + 2, self.value)
            row[-2], row[-1] = self.weight, 0.5
            scale = fixedpoint.scale_for(len(request.participants), 1.0e4)
            self.agents._inputs[self.k] = fixedpoint.encode(row, scale, 1.0e4)
        return answers


def run_rounds(
    run: RunConfig, sides: dict[int, HonestSide], *, weighted: bool = False
) -> tuple[list[RoundRecord], torch.Tensor, SecurePool]:
    """The run's rounds over these sides from θ̃ = 0: every round's record, the final θ̃."""
    records: list[RoundRecord] = []
    coordinator, pool = coordinator_of(run, sides, records, weighted=weighted)
    theta = coordinator.run_rounds()
    return records, theta, pool


def coordinator_of(
    run: RunConfig,
    sides: dict[int, HonestSide],
    records: list[RoundRecord],
    *,
    weighted: bool = False,
) -> tuple[Coordinator, SecurePool]:
    """A coordinator over these sides from θ̃ = 0 that appends each round's record."""
    pool = SecurePool(run, sides)
    coordinator = Coordinator(
        run=run,
        pool=pool,  # type: ignore[arg-type]
        strategy=make_strategy(run.strategy, run=run),
        theta=torch.zeros(NUM_PARAMS),
        on_round=[lambda record, theta: records.append(record)],
        privacy=PrivateRounds(run, weighted=weighted),
    )
    return coordinator, pool


def settings(*extra: str, mode: str = "secagg", k: int = K, rounds: int = 1) -> RunConfig:
    base = [f"privacy={mode}", "agents=homogeneous10", f"agents.num_agents={k}"]
    return compose([*base, f"rounds={rounds}", "eval.every=100", *extra], report=False)


def steps(ks: list[int], weights: np.ndarray | None = None) -> np.ndarray:
    rows = np.stack([step_of(k, NUM_PARAMS).astype(np.float64) for k in ks])
    weights = np.ones(len(ks)) if weights is None else weights
    return weights @ rows / weights.sum()


WEIGHTS = {  # the rogue's (weight, value in every coordinate); the honest weigh 1 each
    "a sum of 2^-46": (2.0**-46 - (K - 1), 1.0e4),
    "a zero sum": (-(K - 1), 0.0),
    "a tiny weight": (2.0**-46, 1.0e4 * 2.0**-46),
    "a huge weight": (1.0e4, 1.0e4),
}


@pytest.mark.parametrize(("weight", "value"), WEIGHTS.values(), ids=WEIGHTS.keys())
def test_a_weight_sum_honest_agents_cannot_send_is_skipped(weight: float, value: float) -> None:
    run = settings()
    sides = {k: HonestSide(run, k) for k in range(K)}
    sides[ROGUE] = ForgedInput(run, ROGUE, weight, value)
    records, theta, _ = run_rounds(run, sides)
    assert torch.equal(theta, torch.zeros(NUM_PARAMS)), f"adopted θ̃ up to {theta.abs().max():.3g}"
    row = records[0].to_json()
    assert "weights add up to" in row["secure"]["failed"]
    assert row["agents"] == [] and row["updates"] == 0


def test_honest_weight_sums_are_adopted_weighted_or_not() -> None:
    for weighted in (False, True):
        run = settings(*(["strategy=weighted"] if weighted else []))
        records, theta, _ = run_rounds(
            run, {k: HonestSide(run, k) for k in range(K)}, weighted=weighted
        )
        assert "secure" not in records[0].to_json()
        weights = np.array([3.0 + k for k in range(K)]) if weighted else None
        np.testing.assert_allclose(theta.numpy(), steps(list(range(K)), weights), atol=1e-6)


def test_max_update_norm_bounds_the_secure_average_step() -> None:
    run = settings("server.max_update_norm=1", rounds=2)
    honest = {k: HonestSide(run, k) for k in range(K)}
    records, theta, _ = run_rounds(run, honest)  # the honest steps are ~0.1 long
    assert ["secure" in r.to_json() for r in records] == [False, False]
    sides: dict[int, HonestSide] = {k: HonestSide(run, k) for k in range(K)}
    sides[ROGUE] = ForgedInput(run, ROGUE, 1.0, 1.0e4)  # a right weight, a step of 10⁴
    records, theta, _ = run_rounds(run, sides)
    assert torch.equal(theta, torch.zeros(NUM_PARAMS)), f"adopted θ̃ up to {theta.abs().max():.3g}"
    assert all("server.max_update_norm" in r.to_json()["secure"]["failed"] for r in records)


# --- distributed noise is sized from the agents that run the protocol ---------------------------


def test_dp_secagg_sizes_the_noise_from_the_registered_agents() -> None:
    # 10 agents selected, 5 registered: each of the 5 adds 1/4 of σC's variance (all but the
    # ⌊(0.1 + 0.1) · 5⌋ = 1 colluder or drop-out the round tolerates), and the round's 5 inputs
    # carry more than σC, so it is unmasked and adopted
    run = settings("privacy.noise_multiplier=1", "privacy.noise_seed=3", mode="dp_secagg", k=10)
    sides = {k: HonestSide(run, k) for k in range(5)}
    records, _, pool = run_rounds(run, sides)
    private = pool.sent[0]
    assert private is not None
    rounds = PrivateRounds(run, weighted=False)
    sigma_c = rounds.update_multiplier * rounds.clip
    assert noise_shares(run.privacy.secagg, 5) == 4
    assert private.noise_std == pytest.approx(sigma_c / np.sqrt(4))
    row = records[0].to_json()
    assert "secure" not in row and row["privacy"]["inputs"] == 5
    assert row["privacy"]["rounds_accounted"] == 1


def test_too_few_noise_shares_are_never_unmasked_nor_accounted() -> None:
    # 5 registered, 4 noise shares needed; three drop before their masked input: 2 inputs carry
    # half of σC's variance: no unmasking request goes out, the round is skipped, not accounted
    run = settings("privacy.noise_multiplier=1", "privacy.noise_seed=3", mode="dp_secagg")
    asked: list[int] = []

    def gone_after_keys(request: Message, honest: list[Reply]) -> list[Reply]:
        return honest if isinstance(request, Train | ShareRequest) else []

    def watch(request: Message, honest: list[Reply]) -> list[Reply]:
        if isinstance(request, UnmaskRequest):
            asked.append(request.round)
        return honest

    sides: dict[int, HonestSide] = {k: RogueSide(run, k, watch) for k in (0, 1)}
    sides.update({k: RogueSide(run, k, gone_after_keys) for k in (2, 3, 4)})
    records, theta, _ = run_rounds(run, sides)
    assert asked == []
    row = records[0].to_json()
    assert "noise shares reach σC" in row["secure"]["failed"]
    assert row["privacy"].get("rounds_accounted", 0) == 0
    assert torch.equal(theta, torch.zeros(NUM_PARAMS))


# --- a failed round is skipped and recorded; the run goes on, up to a bound ----------------------


class Silent(HonestSide):
    """Agent k, registered, that answers nothing in the rounds listed."""

    def __init__(self, run: RunConfig, k: int, rounds: set[int]) -> None:
        super().__init__(run, k)
        self.rounds = rounds

    def answer(self, request: Message) -> list[Reply]:
        return [] if request.round in self.rounds else super().answer(request)  # type: ignore[union-attr]


def test_a_failed_round_is_skipped_and_recorded_and_the_run_goes_on() -> None:
    run = settings(rounds=3)
    sides = {k: Silent(run, k, {2}) for k in range(K)}  # round 2: no input arrives
    records, theta, _ = run_rounds(run, sides)
    rows = [r.to_json() for r in records]
    assert [r["round"] for r in rows] == [1, 2, 3]
    assert "secure" not in rows[0] and "secure" not in rows[2]
    assert rows[1]["secure"] == {"failed": "0 agents advertised keys, fewer than 1"}
    assert rows[1]["agents"] == [] and rows[1]["updates"] == 0
    # rounds 1 and 3 each took the mean step (the sides step alike every round)
    np.testing.assert_allclose(theta.numpy(), 2 * steps(list(range(K))), atol=1e-5)


def test_rounds_that_keep_failing_stop_the_run_in_one_line() -> None:
    run = settings("server.max_failed_rounds=2", rounds=6)
    sides: dict[int, HonestSide] = {k: Silent(run, k, {2, 3, 4, 5, 6}) for k in range(K)}
    records: list[RoundRecord] = []
    coordinator, _ = coordinator_of(run, sides, records)
    with pytest.raises(FederationError, match=r"server.max_failed_rounds=2.*θ̃ of round 1 kept"):
        coordinator.run_rounds()
    assert [r.round for r in records] == [1, 2, 3]  # round 4, the third in a row, stops it
    np.testing.assert_allclose(coordinator.theta.numpy(), steps(list(range(K))), atol=1e-5)


def test_a_wrong_seed_commitment_drops_only_its_sender() -> None:
    # the rogue advertises a commitment to another seed (its own program then refuses to share
    # under it): the honest inputs are summed exactly
    def wrong_commitment(m: MaskKeys) -> np.ndarray:
        return np.full_like(m.seed_commitments, 7)

    rogue = tamper(MaskKeys, seed_commitments=wrong_commitment)
    answers = secure_round(run_of(), sides_with(rogue))
    assert_honest_mean(answers, HONEST)


def test_shares_outvote_a_seed_commitment_that_matches_no_t_of_them() -> None:
    """On the server's side alone: a commitment no t shares match (its owner lied) falls back
    to the shares, so the owner's input is still unmasked."""
    from fedhpg.common.privacy import secagg

    agents = {k: secagg.SecAggAgent(k) for k in range(5)}
    mask_keys = {k: a.advertise(1) for k, a in agents.items()}
    honest = {k: a.seed_commitment(1) for k, a in agents.items()}
    setup = secagg.RoundSetup(
        round=1,
        participants=tuple(range(5)),
        channel_keys={k: a.channel_public for k, a in agents.items()},
        mask_keys=mask_keys,
        seed_commitments=honest,
        length=3,
        neighbours=4,
        threshold=3,
    )
    server = secagg.SecAggRound(
        dataclasses.replace(setup, seed_commitments={**honest, 2: bytes(32)})
    )
    for k, agent in agents.items():
        server.add_keys(k, agent.share_keys(setup))
    words = {k: np.full(3, k + 1, np.uint64) for k in agents}
    for k, agent in agents.items():
        server.add_masked(k, agent.mask(1, words[k], *server.routed(k)))
    dropped, included = server.unmask_request()
    for k in included:
        server.add_reveal(k, agents[k].reveal(1, dropped, included))
    assert np.array_equal(server.total(), np.full(3, 15, np.uint64))
