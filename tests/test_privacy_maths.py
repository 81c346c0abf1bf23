"""The privacy maths on its own: clipping and noise, the accountant against the library's
numbers and published ones, fixed point, Shamir shares, the masks' cryptography and the secure
aggregation protocol (exact sums, dropouts, a masked input that says nothing of its input)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import brentq
from scipy.stats import chisquare, norm

from fedhpg.common.privacy import (
    accounting,
    contribution,
    dp,
    fixedpoint,
    masks,
    secagg,
    shamir,
)
from fedhpg.common.privacy.accounting import Sampling

# --- clipping and noise ---------------------------------------------------------------------------


def test_clip_rows_bounds_norms_and_keeps_directions() -> None:
    rows = torch.tensor([[3.0, 4.0], [0.3, 0.4], [0.0, 0.0]])
    clipped, norms = dp.clip_rows(rows, 1.0)
    assert norms.tolist() == pytest.approx([5.0, 0.5, 0.0])
    assert clipped[0].tolist() == pytest.approx([0.6, 0.8])  # scaled to norm 1
    assert clipped[1].tolist() == pytest.approx([0.3, 0.4])  # inside: unchanged
    assert clipped[2].tolist() == [0.0, 0.0]


def test_distributed_noise_sums_to_the_central_std() -> None:
    # 10 agents each adding N(0, (σC)²/10): the sum's std is σC. 20,000 draws: the sample
    # std's relative standard error is 1/sqrt(2·20,000) = 0.5%, the tolerance 4 of them.
    generator = dp.noise_generator(seed=(1,))
    total_std, agents, draws = 2.5, 10, 20_000
    each = dp.per_agent_std(total_std, agents)
    sums = sum(dp.gaussian(generator, draws, each) for _ in range(agents))
    assert float(np.std(sums)) == pytest.approx(total_std, rel=4 / math.sqrt(2 * draws))


def test_unseeded_noise_differs_between_generators() -> None:
    a, b = dp.noise_generator(), dp.noise_generator()
    assert not np.array_equal(dp.gaussian(a, 8, 1.0), dp.gaussian(b, 8, 1.0))


def test_adaptive_clipping_keeps_the_total_noise_multiplier() -> None:
    sigma, count_std = 1.0, 2.0
    update = dp.update_noise_multiplier(sigma, count_std)
    assert update**-2 + (2 * count_std) ** -2 == pytest.approx(sigma**-2)
    assert dp.update_noise_multiplier(sigma, None) == sigma
    with pytest.raises(ValueError, match="count's noise"):
        dp.update_noise_multiplier(1.0, 0.4)
    # the clip grows while more than the target quantile is clipped, shrinks otherwise
    assert dp.next_clip(1.0, 0.2, 0.5, 0.2) == pytest.approx(math.exp(0.06))
    assert dp.next_clip(1.0, 0.9, 0.5, 0.2) < 1.0


def _worst_move(sigma: float, count_std: float, *, replace: bool) -> float:
    """The largest ‖(f − f′)/std‖ of a round's released sum and centred count between
    neighbouring rounds, measured from the contributions themselves (the weight word is not
    released: the average's denominator is public)."""
    clip = 0.5
    update_std = dp.update_noise_multiplier(sigma, count_std) * clip
    stds = np.array([update_std] * 4 + [count_std])
    settings = contribution.RoundPrivacy(clip=clip)
    rng = np.random.default_rng(5)
    others = [torch.from_numpy(rng.normal(0, 0.2, 4)) for _ in range(6)]

    def released(updates: list[torch.Tensor]) -> np.ndarray:
        total = np.sum([contribution.contribution(u, 1, settings) for u in updates], axis=0)
        return np.delete(total, -contribution.EXTRA)

    def of_norm(norm: float, direction: int) -> torch.Tensor:
        update = torch.zeros(4, dtype=torch.float64)
        update[direction] = norm
        return update

    # one agent inside the clip (b = 1) and one far outside (b = 0), in opposite directions
    inside, outside = of_norm(clip * (1 - 1e-12), 0), of_norm(-3.0, 0)
    if replace:
        moved = released([*others, inside]) - released([*others, outside])
    else:
        moved = released([*others, inside]) - released(others)
    return float(np.linalg.norm(moved / stds))


@pytest.mark.parametrize(("sigma", "count_std"), [(1.0, 2.0), (2.0, 2.0), (0.8, 5.0)])
def test_the_sum_and_the_centred_count_are_one_gaussian_of_multiplier_sigma(
    sigma: float, count_std: float
) -> None:
    # the accountant composes multiplier σ for adding or removing one agent (sensitivity
    # 1/σ in units of the noise) and σ/2 for replacing one (2/σ): the release of the sum and
    # the count together must move by exactly that much, no more
    assert _worst_move(sigma, count_std, replace=False) == pytest.approx(1 / sigma, rel=1e-9)
    assert _worst_move(sigma, count_std, replace=True) == pytest.approx(2 / sigma, rel=1e-9)


def test_the_average_gives_the_fraction_unclipped_from_the_centred_count() -> None:
    settings = contribution.RoundPrivacy(clip=1.0)
    rows = [
        contribution.contribution(torch.tensor([n, 0.0], dtype=torch.float64), 1, settings)
        for n in (0.1, 0.5, 2.0, 3.0, 0.9)
    ]
    assert [row[-1] for row in rows] == [0.5, 0.5, -0.5, -0.5, 0.5]  # b − ½
    step, fraction = contribution.average(np.sum(rows, axis=0), 5.0)
    assert fraction == pytest.approx(3 / 5)
    assert step.tolist() == pytest.approx([(0.1 + 0.5 + 1.0 + 1.0 + 0.9) / 5, 0.0])
    noisy = np.sum(rows, axis=0)
    noisy[-1] += 10.0  # noise can take the count past every agent: the fraction stays in [0, 1]
    assert contribution.average(noisy, 5.0)[1] == 1.0
    noisy[-1] -= 30.0
    assert contribution.average(noisy, 5.0)[1] == 0.0


def test_the_clip_steps_from_a_clamped_fraction() -> None:
    assert dp.next_clip(1.0, 1.7, 0.5, 0.2) == dp.next_clip(1.0, 1.0, 0.5, 0.2)
    assert dp.next_clip(1.0, -0.4, 0.5, 0.2) == pytest.approx(math.exp(0.1))


def test_secure_noise_costs_a_few_numpy_calls_not_a_loop() -> None:
    # a draw the size of a 100k-parameter update: one os.urandom call, the right size
    draws = dp.gaussian(dp.SecureNoise(), 100_000, 3.0)
    assert draws.shape == (100_000,) and draws.dtype == np.float64
    assert dp.gaussian(dp.SecureNoise(), 7, 0.0).tolist() == [0.0] * 7
    assert dp.standard_normals(5).shape == (5,)


# --- accounting -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "sampling",
    [
        Sampling(kind="all", population=50),
        Sampling(kind="fixed", population=100, sample=10),
        Sampling(kind="poisson", population=1000, rate=0.05),
    ],
)
def test_epsilon_is_the_librarys_own(sampling: Sampling) -> None:
    import dp_accounting

    for sigma, rounds in ((1.3, 7), (0.9, 60)):
        library = accounting.make_accountant("rdp", sampling)
        library.compose(
            dp_accounting.SelfComposedDpEvent(accounting.round_event(sigma, sampling), rounds)
        )
        ours = accounting.epsilon(sigma, sampling, rounds, 1e-5)
        assert ours == pytest.approx(library.get_epsilon(1e-5), rel=1e-12)


def test_abadi_et_al_published_epsilon() -> None:
    # Abadi et al. 2016, "Deep learning with differential privacy", Section 3.1: q = 0.01,
    # σ = 4, δ = 1e-5, T = 10,000 steps give ε ≈ 1.26 with the moments accountant (9.34 by
    # the strong composition theorem). RDP (a refinement of the moments accountant) and the
    # privacy-loss distribution (tighter still) must not exceed it, nor fall far below.
    sampling = Sampling(kind="poisson", population=60_000, rate=0.01)
    rdp = accounting.epsilon(4.0, sampling, 10_000, 1e-5)
    pld = accounting.epsilon(4.0, sampling, 10_000, 1e-5, kind="pld")
    assert 0.75 * 1.26 < pld <= rdp <= 1.26


def test_gaussian_composition_against_the_exact_curve() -> None:
    # No sampling: T rounds of multiplier σ are one Gaussian mechanism of σ/√T, whose exact
    # δ(ε) is Balle and Wang's (2018, Theorem 8). PLD is near exact, RDP an upper bound.
    sigma, rounds, delta = 4.0, 25, 1e-5
    mu = math.sqrt(rounds) / sigma

    def exact_delta(eps: float) -> float:
        return float(norm.cdf(-eps / mu + mu / 2) - math.exp(eps) * norm.cdf(-eps / mu - mu / 2))

    sampling = Sampling(kind="all", population=10)
    pld = accounting.epsilon(sigma, sampling, rounds, delta, kind="pld")
    rdp = accounting.epsilon(sigma, sampling, rounds, delta)
    assert exact_delta(pld) == pytest.approx(delta, rel=0.02)
    assert rdp >= pld
    assert exact_delta(rdp) <= delta


def test_calibration_meets_the_target_and_no_more_noise() -> None:
    sampling = Sampling(kind="fixed", population=100, sample=10)
    delta = accounting.default_delta(100)
    sigma = accounting.calibrate(4.0, sampling, 50, delta)
    assert accounting.epsilon(sigma, sampling, 50, delta) <= 4.0
    assert accounting.epsilon(sigma * 0.99, sampling, 50, delta) > 4.0
    assert delta == 1e-5  # min(1/(10K), 1e-5)


@pytest.mark.parametrize("participations", [1, 9, 40])
def test_epsilon_against_a_party_that_knows_the_sample(participations: int) -> None:
    # no amplification: for replacing one agent each of its rounds is a Gaussian of
    # sensitivity 2C and std σC, so n rounds are one of μ = 2√n/σ; the exact curve (Balle and
    # Wang 2018) gives the least ε, the RDP figure may only be above it, and within 30 %
    sigma, delta = 3.0, 1e-5
    sampling = Sampling(kind="fixed", population=100, sample=10)
    mu = 2 * math.sqrt(participations) / sigma

    def excess(eps: float) -> float:
        return float(norm.cdf(-eps / mu + mu / 2) - math.exp(eps) * norm.cdf(-eps / mu - mu / 2))

    exact = brentq(lambda eps: excess(eps) - delta, 0.0, 200.0)
    known = accounting.epsilon(sigma, sampling, participations, delta, known=True)
    assert exact <= known <= 1.3 * exact
    pld = accounting.epsilon(sigma, sampling, participations, delta, "pld", known=True)
    assert pld == pytest.approx(exact, rel=0.02)
    # the same sample, hidden: amplified, far below
    assert accounting.epsilon(sigma, sampling, participations, delta) < known
    everyone = Sampling(kind="all", population=100)
    assert accounting.epsilon(sigma, everyone, 5, delta, known=True) == accounting.epsilon(
        sigma, everyone, 5, delta
    )


def test_the_default_delta() -> None:
    assert accounting.default_delta(4) == 1e-5
    assert accounting.default_delta(10_000) == 1e-5
    assert accounting.default_delta(1_000_000) == pytest.approx(1e-7)


def test_pld_refuses_sampling_without_replacement() -> None:
    with pytest.raises(accounting.AccountingError, match="without replacement"):
        accounting.make_accountant("pld", Sampling(kind="fixed", population=10, sample=2))


# --- fixed point ----------------------------------------------------------------------------------


def test_fixed_point_sums_exactly_through_wraparound() -> None:
    rng = np.random.default_rng(0)
    values = rng.uniform(-3.0, 3.0, size=(50, 7))
    scale = fixedpoint.scale_for(50, 3.0)
    assert 50 * 3.0 * scale <= 2.0**62
    words = [fixedpoint.encode(row, scale, 3.0) for row in values]
    total = np.zeros(7, dtype=np.uint64)
    for w in words:
        fixedpoint.add(total, w)
    exact = [sum(int(np.rint(row[i] * scale)) for row in values) for i in range(7)]
    assert total.view(np.int64).tolist() == exact  # no bit lost, negatives wrapped and back
    assert np.allclose(fixedpoint.decode(total, scale), values.sum(axis=0), atol=50 / scale)
    assert fixedpoint.decode(
        fixedpoint.encode(np.array([9.0, -9.0]), scale, 3.0), scale
    ).tolist() == [
        3.0,
        -3.0,
    ]


# --- Shamir ---------------------------------------------------------------------------------------


def test_any_threshold_shares_recover_the_secret() -> None:
    secret = bytes(range(32))
    xs = list(range(1, 8))
    shares = dict(zip(xs, shamir.split(secret, xs, 4), strict=True))
    for subset in ([1, 2, 3, 4], [7, 5, 3, 1], [2, 4, 6, 7]):
        assert shamir.combine({x: shares[x] for x in subset}, 4) == secret
    with pytest.raises(ValueError, match="fewer than the threshold"):
        shamir.combine({x: shares[x] for x in (1, 2, 3)}, 4)
    # three shares with a wrong fourth give a different value: the fourth was needed
    forged = {**{x: shares[x] for x in (1, 2, 3)}, 4: shares[5]}
    with pytest.raises(ValueError):
        assert shamir.combine(forged, 4) != secret
        raise ValueError


# --- the masks' cryptography ----------------------------------------------------------------------


def test_key_agreement_masks_and_channel() -> None:
    a, b = masks.new_private_key(), masks.new_private_key()
    purpose = masks.mask_purpose(3, 1, 2)
    key = masks.agree(a, masks.public_key(b), purpose)
    assert key == masks.agree(b, masks.public_key(a), masks.mask_purpose(3, 2, 1))
    assert key != masks.agree(a, masks.public_key(b), masks.mask_purpose(4, 1, 2))
    assert np.array_equal(masks.expand(key, 9), masks.expand(key, 9))
    sealed = masks.seal(key, b"share", b"header")
    assert masks.open_sealed(key, sealed, b"header") == b"share"
    tampered = sealed[:-1] + bytes([sealed[-1] ^ 1])
    with pytest.raises(masks.ChannelError):
        masks.open_sealed(key, tampered, b"header")
    with pytest.raises(masks.ChannelError):
        masks.open_sealed(key, sealed, b"another header")


# --- the protocol ---------------------------------------------------------------------------------


def _round(
    n: int,
    length: int,
    inputs: dict[int, np.ndarray],
    *,
    drop_before_input: set[int] = frozenset(),  # type: ignore[assignment]
    drop_after_input: set[int] = frozenset(),  # type: ignore[assignment]
    neighbours: int | None = None,
    round_index: int = 1,
) -> tuple[np.ndarray, list[int], dict[int, np.ndarray]]:
    agents = {k: secagg.SecAggAgent(k) for k in range(n)}
    setup = _setup(agents, round_index, length, neighbours)
    server = secagg.SecAggRound(setup)
    for k, agent in agents.items():
        server.add_keys(k, agent.share_keys(setup))
    seen: dict[int, np.ndarray] = {}
    for k, agent in agents.items():
        if k not in drop_before_input:
            keys, sealed = server.routed(k)
            seen[k] = agent.mask(round_index, inputs[k], keys, sealed)
            server.add_masked(k, seen[k])
    dropped, included = server.unmask_request()
    for k in included:
        if k not in drop_after_input:
            server.add_reveal(k, agents[k].reveal(round_index, dropped, included))
    return server.total(), included, seen


def _setup(
    agents: dict[int, secagg.SecAggAgent], round_index: int, length: int, neighbours: int | None
) -> secagg.RoundSetup:
    """Every agent advertises a mask key; the setup of t = ⌊k/2⌋ + 1 of k neighbours (all by
    default) over the graph they draw."""
    mask_keys = {k: agent.advertise(round_index) for k, agent in agents.items()}
    commitments = {k: agent.seed_commitment(round_index) for k, agent in agents.items()}
    k = len(agents) - 1 if neighbours is None else neighbours
    return secagg.RoundSetup(
        round=round_index,
        participants=tuple(sorted(agents)),
        channel_keys={v: a.channel_public for v, a in agents.items()},
        mask_keys=mask_keys,
        seed_commitments=commitments,
        length=length,
        neighbours=k,
        threshold=k // 2 + 1,
    )


def _words(rng: np.random.Generator, n: int, length: int) -> dict[int, np.ndarray]:
    return {k: rng.integers(0, 2**63, length, dtype=np.uint64) for k in range(n)}


def _plain_sum(inputs: dict[int, np.ndarray], included: list[int]) -> np.ndarray:
    total = np.zeros(len(next(iter(inputs.values()))), dtype=np.uint64)
    for k in included:
        fixedpoint.add(total, inputs[k])
    return total


@pytest.mark.parametrize(
    ("n", "after", "before", "neighbours"),
    [
        (10, {4}, set(), None),  # one agent drops after sending its input
        (20, {1, 7}, set(), None),  # 10 %
        (10, {0, 5, 9}, set(), None),  # 30 %
        (10, {2}, {6, 8}, None),  # and two that never sent an input
        # SecAgg+: 10 neighbours each, t = 6; 4 dropped ≤ k − t, so every agent keeps t
        # answering neighbours whatever ring the round's keys draw (with 8 neighbours,
        # t = 5, a draw placing all 4 dropped agents beside one agent fails the round)
        (30, {3, 11, 29}, {17}, 10),
    ],
)
def test_the_sum_is_exact_despite_dropouts(
    n: int, after: set[int], before: set[int], neighbours: int | None
) -> None:
    rng = np.random.default_rng(n)
    inputs = _words(rng, n, 33)
    total, included, _ = _round(
        n, 33, inputs, drop_after_input=after, drop_before_input=before, neighbours=neighbours
    )
    assert included == sorted(set(range(n)) - before)
    assert np.array_equal(total, _plain_sum(inputs, included))


def test_too_many_dropouts_cannot_be_unmasked() -> None:
    rng = np.random.default_rng(3)
    inputs = _words(rng, 6, 4)
    # t = ⌊0.5·5⌋ + 1 = 3 shares of each secret; 4 of 6 revealing nothing leaves 2
    with pytest.raises(secagg.SecAggError, match="fewer than the threshold"):
        _round(6, 4, inputs, drop_after_input={0, 1, 2, 3})


def test_an_agent_never_reveals_both_secrets_of_a_neighbour() -> None:
    agents = {k: secagg.SecAggAgent(k) for k in range(4)}
    setup = _setup(agents, 2, 2, None)
    server = secagg.SecAggRound(setup)
    for k, agent in agents.items():
        server.add_keys(k, agent.share_keys(setup))
    for k, agent in agents.items():
        agent.mask(2, np.zeros(2, np.uint64), *server.routed(k))
    agents[0].reveal(2, [1], [0, 2, 3])
    with pytest.raises(secagg.SecAggError, match="already revealed"):
        agents[0].reveal(2, [], [0, 1, 2, 3])
    with pytest.raises(secagg.SecAggError, match="disjoint"):
        agents[1].reveal(2, [2], [1, 2, 3])


def test_the_servers_view_of_one_masked_input_is_uniform() -> None:
    # Agent 0's true input is a fixed-point update whose first word takes one of two very
    # different values; over 1,500 rounds its masked input's top 4 bits must be uniform over
    # the 16 bins (chi-square) and uncorrelated with the true value. The same statistics on
    # the unmasked words fail, so the test can tell.
    rng = np.random.default_rng(11)
    draws, length = 1500, 2
    scale = fixedpoint.scale_for(3, 1.0)
    truths, views = [], []
    for draw in range(draws):
        value = rng.choice([-0.9, 0.7])
        inputs = {k: fixedpoint.encode(rng.uniform(-1, 1, length), scale, 1.0) for k in range(3)}
        inputs[0] = fixedpoint.encode(np.array([value, 0.0]), scale, 1.0)
        _, _, seen = _round(3, length, inputs, round_index=draw + 1)
        truths.append(value)
        views.append(seen[0][0])

    def bins_and_correlation(words: list) -> tuple[float, float]:
        top = np.array([int(w) >> 60 for w in words])
        p_uniform = float(chisquare(np.bincount(top, minlength=16)).pvalue)
        as_real = np.array([int(w) / 2.0**64 for w in words])
        return p_uniform, float(np.corrcoef(truths, as_real)[0, 1])

    p_masked, r_masked = bins_and_correlation(views)
    assert p_masked > 1e-3
    assert abs(r_masked) < 4 / math.sqrt(draws)  # 4 standard errors of r under independence
    plain = [fixedpoint.encode(np.array([t]), scale, 1.0)[0] for t in truths]
    p_plain, r_plain = bins_and_correlation(plain)
    assert p_plain < 1e-3 and abs(r_plain) > 0.9
