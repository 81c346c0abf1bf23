"""SecAgg+'s neighbour graph and threshold (common/privacy/graph.py) and the signed key
advertisements (common/privacy/signing.py): the bounds against a simulation, a graph nobody
can predict before the round's keys are fixed, thresholds refused where they guarantee nothing.
"""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest

pytest.importorskip("cryptography")
pytest.importorskip("scipy")

from fedhpg.common.privacy import signing
from fedhpg.common.privacy.graph import (
    COMPLETE_UP_TO,
    PRIVACY_BITS,
    GraphError,
    Tolerance,
    _tail,
    bounds,
    graph_seed,
    neighbour_graph,
    plan_graph,
)

DEFAULT = Tolerance(corruption=0.1, dropout=0.1)


def _keys(count: int, rng: np.random.Generator) -> dict[int, bytes]:
    return {k: rng.bytes(32) for k in range(count)}


def test_small_rounds_use_the_complete_graph_with_a_threshold_that_splits_no_secret() -> None:
    for n in (2, 3, 4, 10, COMPLETE_UP_TO):
        plan = plan_graph(n, DEFAULT)
        assert plan.complete and plan.neighbours == n - 1
        colluders = DEFAULT.colluders(n)
        # a deviating server asking half the honest neighbours for each secret gets t of
        # both only when colluders reach 2t − k: never, with this t
        assert colluders < 2 * plan.threshold - plan.neighbours
        assert DEFAULT.silent(n) <= plan.neighbours - plan.threshold


@pytest.mark.parametrize("agents", [100, 1_000, 10_000])
def test_large_rounds_take_the_fewest_neighbours_that_meet_both_bounds(agents: int) -> None:
    plan = plan_graph(agents, DEFAULT)
    assert not plan.complete
    assert plan.exposure <= 2.0**-PRIVACY_BITS and plan.failure <= 2.0**-20
    assert 2 * plan.threshold > plan.neighbours
    fewer = plan.neighbours - 2
    assert all(
        bounds(agents, fewer, t, DEFAULT).exposure > 2.0**-PRIVACY_BITS
        or bounds(agents, fewer, t, DEFAULT).failure > 2.0**-20
        for t in range(fewer // 2 + 1, fewer + 1)
    ), "two neighbours fewer would have met the bounds too"


def test_the_guides_sixteen_neighbours_were_unsafe_at_a_fifth_corrupted_or_dropped() -> None:
    """An outside audit measured, at n = 1,000 and k = 16 (t = 9): 20 % corruption exposed
    some input in 38.5 % of rounds, 20 % dropout failed 89 % of them. The bounds must be no
    lower than what was measured, and the setting is refused."""
    tolerance = Tolerance(corruption=0.2, dropout=0.0)
    assert bounds(1_000, 16, 9, tolerance).exposure >= 0.385
    assert bounds(1_000, 16, 9, Tolerance(corruption=0.0, dropout=0.2)).failure >= 0.89
    with pytest.raises(GraphError, match="cannot both hide every input"):
        plan_graph(1_000, Tolerance(corruption=0.2, dropout=0.2), neighbours=16, threshold=0.5)


def test_a_threshold_of_one_half_is_refused_where_one_colluder_and_split_requests_expose() -> None:
    """n = 10, complete (k = 9), threshold 0.5 → t = 5: one colluder plus four honest
    neighbours asked for each secret give the server 5 shares of both."""
    with pytest.raises(GraphError, match=r"t = 6 of k = 9 would"):
        plan_graph(10, DEFAULT, threshold=0.5)
    assert plan_graph(10, DEFAULT, threshold=0.6).threshold == 6
    with pytest.raises(GraphError):
        plan_graph(10, DEFAULT, threshold=0.3)  # no colluder needed at all


def test_the_exposure_bound_holds_against_a_simulation() -> None:
    """One agent's colluding neighbours on the drawn ring, over 2,000 draws of the graph and
    the colluders, at a deliberately weak (k, t): the tail the bound sums is what happens."""
    n, k, t = 200, 12, 8
    tolerance = Tolerance(corruption=0.25, dropout=0.0)
    colluders = tolerance.colluders(n)
    rng = np.random.default_rng(5)
    draws, exposed = 2_000, 0
    for _ in range(draws):
        graph = neighbour_graph(range(n), k, rng.bytes(32))
        corrupt = set(rng.choice(np.arange(1, n), size=colluders, replace=False).tolist())
        exposed += len(corrupt & set(graph[0])) >= 2 * t - k
    per_agent = _tail(n - 1, colluders, k, 2 * t - k)  # the term the union bound sums
    frequency = exposed / draws
    std = (per_agent * (1 - per_agent) / draws) ** 0.5
    assert 0.1 < per_agent < 0.9
    assert abs(frequency - per_agent) < 4 * std, (frequency, per_agent)
    assert bounds(n, k, t, tolerance).exposure >= min(1.0, n * per_agent)


def test_the_ring_is_unknown_until_every_mask_key_is_fixed() -> None:
    """Nine colluders placed in advance around a target, in the order a public rule would
    give (here: the previous release's SHA-256 of (round, index)), end up among its
    neighbours no more often than chance."""
    import hashlib

    n, round_index, target = 1_000, 7, 123
    plan = plan_graph(n, DEFAULT)
    public_ring = sorted(
        range(n), key=lambda u: hashlib.sha256(struct.pack("<qq", round_index, u)).digest()
    )
    where = public_ring.index(target)
    chosen = {public_ring[(where + step) % n] for step in (-5, -4, -3, -2, -1, 1, 2, 3, 4)}
    # the control: on the public ring with the guide's k = 16 (t = 9) they were 9 of the
    # target's 16 neighbours, past the 2t − k = 2 that exposes it, in every round
    old = {public_ring[(where + step) % n] for step in range(-8, 9)} - {target}
    assert chosen <= old and len(chosen) >= 2 * 9 - 16
    rng = np.random.default_rng(11)
    hits = []
    for _ in range(50):
        seed = graph_seed(round_index, _keys(n, rng))
        hits.append(len(chosen & set(neighbour_graph(range(n), plan.neighbours, seed)[target])))
    # by chance: 9 · k / (n − 1) ≈ 1.8 of them; never the 2t − k the exposure needs
    assert max(hits) < 2 * plan.threshold - plan.neighbours
    assert np.mean(hits) < 9 * plan.neighbours / (n - 1) + 1.5


def test_the_seed_depends_on_every_participants_mask_key() -> None:
    rng = np.random.default_rng(3)
    keys = _keys(50, rng)
    seed = graph_seed(1, keys)
    for agent in (0, 17, 49):
        changed = dict(keys)
        changed[agent] = os.urandom(32)
        assert graph_seed(1, changed) != seed
    assert graph_seed(2, keys) != seed
    graph = neighbour_graph(range(50), 8, seed)
    assert all(len(near) == 8 and u not in near for u, near in graph.items())
    assert all(u in graph[v] for u, near in graph.items() for v in near)  # symmetric


# -- signed advertisements -------------------------------------------------------------------


def test_a_signature_binds_a_key_to_its_agent_round_and_purpose() -> None:
    private = signing.new_signing_key()
    roster = signing.Roster({3: signing.verifying_key(private)})
    mask_key, channel_key, seed = os.urandom(32), os.urandom(32), os.urandom(32)
    signature = signing.sign(private, signing.mask_statement(5, 3, mask_key, channel_key, seed))
    roster.check(3, signing.mask_statement(5, 3, mask_key, channel_key, seed), signature)
    for statement in (
        signing.mask_statement(6, 3, mask_key, channel_key, seed),  # another round
        signing.mask_statement(5, 3, os.urandom(32), channel_key, seed),  # a substituted key
        signing.mask_statement(5, 3, mask_key, os.urandom(32), seed),  # another channel key
        signing.mask_statement(5, 3, mask_key, channel_key, os.urandom(32)),  # commitment
        signing.mask_statement(5, 4, mask_key, channel_key, seed),  # another agent
    ):
        with pytest.raises(signing.SignatureError):
            roster.check(3, statement, signature)
    with pytest.raises(signing.SignatureError, match="no signing key"):
        roster.check(4, signing.mask_statement(5, 4, mask_key, channel_key, seed), signature)


def test_fedhpg_keys_writes_a_roster_that_binds_hosts_and_named_agents(tmp_path) -> None:
    from fedhpg.server.commands.keys import run

    assert run([str(tmp_path / "k"), "--agents", "10", "--per-host", "5"]) == 0
    roster = signing.load_roster(tmp_path / "k" / signing.SIGNERS_DIR)
    assert sorted(roster.keys) == list(range(10))
    host = signing.load_signing_key(tmp_path / "k" / "host-0-4.sign_secret")
    statement = signing.mask_statement(1, 2, os.urandom(32), os.urandom(32), os.urandom(32))
    roster.check(2, statement, signing.sign(host, statement))
    with pytest.raises(signing.SignatureError):
        roster.check(7, statement, signing.sign(host, statement))  # the other host's agent
    assert (tmp_path / "k" / "host-0-4.sign_secret").stat().st_mode & 0o077 == 0
    (tmp_path / "k" / signing.SIGNERS_DIR / "extra@3.sign").write_text(
        signing.verifying_key(host).hex() + "\n"
    )
    with pytest.raises(signing.SignatureError, match="already has a signing key"):
        signing.load_roster(tmp_path / "k" / signing.SIGNERS_DIR)
