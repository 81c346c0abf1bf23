"""Whether the ε a private run reports holds, against whom it says: the sample of a sampled
``dp`` run never reaches its run directory and is not the public seed's; a ``dp_secagg`` run
reports ε against the server (which picks and sees the sample) beside ε against the released
model; the adaptive clip's count is accounted at its true sensitivity (checked from the
contributions themselves, against the exact curve of the Gaussian mechanism); δ defaults to
at most 10⁻⁵; every noisy release is accounted, also one a crash made the run repeat; the noise
comes from the operating system's CSPRNG, as a sum of Gaussians."""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from scipy.optimize import brentq
from scipy.stats import kstest, norm

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.strategy import ParticipationConfig
from fedhpg.common.privacy import accounting, dp
from fedhpg.common.privacy.contribution import EXTRA, RoundPrivacy, contribution
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api
from fedhpg.server.participation import Participation
from fedhpg.server.pools.inprocess import InProcessPool
from fedhpg.server.privacy import PrivateRounds, sampling_of

SAMPLED = [
    "agents=homogeneous10",
    "agents.budget.batch_size=[4]",
    "strategy.participation.mode=uniform",
    "strategy.participation.per_round=4",
]
SHORT = ["rounds=4", "eval.every=2", "eval.episodes=1", "seed=3"]


def exact_epsilon(mu: float, delta: float) -> float:
    """ε of a Gaussian mechanism of sensitivity over std ``mu`` at ``delta``: the exact curve
    (Balle and Wang 2018, Theorem 8), solved for ε."""

    def excess(eps: float) -> float:
        return float(norm.cdf(-eps / mu + mu / 2) - math.exp(eps) * norm.cdf(-eps / mu - mu / 2))

    return float(brentq(lambda eps: excess(eps) - delta, 0.0, 500.0))


class SelectionSpy:
    """Wraps :meth:`Participation.select` for a test: the true sample of every round."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.rounds: dict[int, list[int]] = {}
        original = Participation.select

        def select(participation: Participation, round_number: int) -> list[int]:
            drawn = original(participation, round_number)
            self.rounds[round_number] = list(drawn)
            return drawn

        monkeypatch.setattr(Participation, "select", select)


# --- 1. the sample is secret where the accounting amplifies by it -----------------------------


def _spellings(sample: list[int]) -> list[bytes]:
    """The ways a file could hold a round's sample: JSON lists, CSV, a plain list."""
    return [
        json.dumps(sample).encode(),
        json.dumps(sample, separators=(",", ":")).encode(),
        ",".join(map(str, sample)).encode(),
        " ".join(map(str, sample)).encode(),
        ", ".join(f"agent-{k}" for k in sample).encode(),
    ]


def test_a_sampled_dp_runs_sample_is_in_nothing_it_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    spy = SelectionSpy(monkeypatch)
    out = tmp_path / "run"
    result = api.run(
        overrides=[*SHORT, *SAMPLED, "privacy=dp", "privacy.noise_multiplier=1"], out_dir=out
    )
    samples = [spy.rounds[r] for r in range(1, 5)]
    assert all(len(s) == 4 for s in samples)
    # not the draw anybody can repeat from the run's public seed (each round matches it with
    # probability 1/210: all four, 210⁻⁴)
    public = Participation(
        ParticipationConfig(mode="uniform", per_round=4), seed=result.config.seed, num_agents=10
    )
    assert samples != [public.select(r) for r in range(1, 5)]
    files = [path for path in out.rglob("*") if path.is_file()]
    assert {"metrics.jsonl", "summary.json", "progress.csv"} <= {p.name for p in files}
    assert any(p.suffix == ".safetensors" for p in files)
    assert any(p.name.startswith("events.out.tfevents") for p in files)
    for path in files:
        data = path.read_bytes()
        for sample in samples:
            for spelling in _spellings(sample):
                assert spelling not in data, (path, sample)
        assert b"agent/" not in data, path  # TensorBoard's per-agent tags
    for record in result.records:
        assert "selected" not in record and record["agents"] == []
        assert "failures" not in record and "stragglers" not in record
        assert record["updates"] == 4 and record["privacy"]["sample"] == "hidden"


def test_the_pools_log_lines_name_no_agent_of_a_hidden_sample(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from fedhpg.server.privacy import hidden_agent_names

    names = [f"agent-{k}" for k in range(12)]
    pool_log = logging.getLogger("fedhpg.server.pools.zmq_pool")
    with caplog.at_level(logging.INFO), hidden_agent_names(names):
        pool_log.warning(
            "round %d aggregated %d of %d updates; stragglers: %s", 3, 2, 4, "agent-11"
        )
        pool_log.warning("rejected the update of %s: %s", "agent-1", "not finite")
    pool_log.warning("rejected the update of %s: %s", "agent-1", "not finite")
    hidden, after = caplog.messages[:2], caplog.messages[2]
    assert hidden == [
        "round 3 aggregated 2 of 4 updates; stragglers: an agent",
        "rejected the update of an agent: not finite",
    ]
    assert after == "rejected the update of agent-1: not finite"  # the filter is gone


def test_dp_secagg_reports_epsilon_against_the_server(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import dp_accounting

    spy = SelectionSpy(monkeypatch)
    out = tmp_path / "run"
    sigma = 1.5
    result = api.run(
        overrides=[*SHORT, *SAMPLED, "privacy=dp_secagg", f"privacy.noise_multiplier={sigma}"],
        out_dir=out,
    )
    delta = result.records[0]["delta"]
    counts = np.zeros(10, dtype=int)
    for record in result.records:
        counts[spy.rounds[record["round"]]] += 1
        # the server knows the sample: no amplification; each round moves the sum of the
        # worst agent's rounds by up to 2C when it is replaced, a Gaussian of multiplier σ/2
        library = dp_accounting.rdp.RdpAccountant()
        library.compose(dp_accounting.GaussianDpEvent(sigma / 2), int(counts.max()))
        assert record["epsilon_server"] == pytest.approx(library.get_epsilon(delta))
        if counts.max() == record["round"]:  # an agent drawn every round: amplified is less
            assert record["epsilon_server"] > record["epsilon"]
        assert record["selected"] == spy.rounds[record["round"]]  # the server's own view
    summary = json.loads((out / "summary.json").read_text())["privacy"]
    assert summary["epsilon_server"] == result.records[-1]["epsilon_server"]
    assert summary["budget_against"] == "model"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    board = EventAccumulator(str(out / "tensorboard"))
    board.Reload()
    logged = [e.value for e in board.Scalars("privacy/epsilon_server")]
    assert logged == pytest.approx([r["epsilon_server"] for r in result.records])


def test_a_budget_against_the_server_caps_the_servers_epsilon() -> None:
    # σ calibrated so that even an agent drawn every round stays within ε = 6 against the server
    budget = ["privacy=dp_secagg", "privacy.epsilon=6", "privacy.budget_against=server"]
    result = api.run(overrides=[*SHORT, *SAMPLED, *budget])
    sigma = result.records[0]["privacy"]["noise_multiplier"]
    delta = result.records[0]["delta"]
    sampling = sampling_of(result.config)
    assert accounting.epsilon(sigma, sampling, 4, delta, known=True) <= 6.0
    assert accounting.epsilon(sigma * 0.99, sampling, 4, delta, known=True) > 6.0
    assert all(r["epsilon_server"] <= 6.0 for r in result.records)
    with pytest.raises(ConfigError, match="trusted") as refused:
        api.resolve_config(overrides=["privacy=dp", "privacy.epsilon=1", *budget[2:]])
    assert refused.value.key == "privacy.budget_against"


def test_noise_seed_makes_a_sampled_dp_run_and_its_resume_bit_exact(tmp_path: Path) -> None:
    seeded = [*SAMPLED, "privacy=dp", "privacy.noise_multiplier=1", "privacy.noise_seed=4"]
    seeded += ["privacy.adaptive_clip=true", "eval.every=2", "eval.episodes=1", "seed=3"]
    whole = api.run(overrides=[*seeded, "rounds=4"])
    again = api.run(overrides=[*seeded, "rounds=4"])
    assert torch.equal(whole.theta, again.theta)
    out = tmp_path / "run"
    api.run(overrides=[*seeded, "rounds=2"], out_dir=out)
    resumed = api.run(overrides=[*seeded, "rounds=4", "resume=true"], out_dir=out)
    assert torch.equal(resumed.theta, whole.theta)
    assert [r["epsilon"] for r in resumed.records] == [r["epsilon"] for r in whole.records]


# --- 2. adaptive clipping's count at its true sensitivity -------------------------------------


def test_the_logged_epsilon_holds_for_the_sum_and_the_count_together() -> None:
    # Every agent every round (add or remove one agent), σ = 2, adaptive clipping: the server
    # releases the clipped sum and the count of unclipped updates, each with its own noise.
    rounds, delta = 3, 1e-5
    result = api.run(
        overrides=[
            "agents=homogeneous10",
            "agents.budget.batch_size=[4]",
            f"rounds={rounds}",
            "eval.every=3",
            "eval.episodes=1",
            "privacy=dp",
            "privacy.noise_multiplier=2",
            f"privacy.delta={delta}",
            "privacy.adaptive_clip=true",
        ]
    )
    assert result.records[0]["agents"][0]["train_return"] == 0.0  # never leaves the agent
    server = PrivateRounds(result.config, weighted=False)
    clip = 0.7
    stds = np.full(5 + 1, server.update_multiplier * clip)
    stds[-1] = server.count_std
    settings = RoundPrivacy(clip=clip)
    rng = np.random.default_rng(0)
    others = [torch.from_numpy(rng.normal(0, 0.3, 5)) for _ in range(9)]

    def released(updates: list[torch.Tensor]) -> np.ndarray:
        total = sum(contribution(u, 1, settings) for u in updates)
        assert isinstance(total, np.ndarray)
        return np.delete(total, -EXTRA)  # the weight is not released (a public denominator)

    worst = 0.0
    for norm_of_one in (0.2, clip * (1 - 1e-9), clip * (1 + 1e-9), 3.0):  # in, on, out
        one = torch.from_numpy(rng.normal(0, 1, 5))
        one *= norm_of_one / float(torch.linalg.vector_norm(one))
        moved = released([*others, one]) - released(others)
        worst = max(worst, float(np.linalg.norm(moved / stds)))
    # the worst neighbour moves the release by ‖·/std‖ = 1/σ: what the accountant composes
    assert worst == pytest.approx(1 / 2.0, rel=1e-6)
    logged = result.records[-1]["epsilon"]
    assert logged >= exact_epsilon(math.sqrt(rounds) * worst, delta)
    everyone = accounting.Sampling(kind="all", population=10)
    assert logged == pytest.approx(accounting.epsilon(1 / worst, everyone, rounds, delta))


# --- 7. δ ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("agents", "delta"), [(4, 1e-5), (10, 1e-5), (1_000_000, 1e-7)])
def test_the_default_delta_is_at_most_1e_5_and_a_tenth_of_1_over_k(
    agents: int, delta: float
) -> None:
    run = api.resolve_config(
        overrides=[
            "agents=homogeneous4",
            f"agents.num_agents={agents}",
            "privacy=dp",
            "privacy.noise_multiplier=1",
        ]
    )
    assert PrivateRounds(run, weighted=False).delta == pytest.approx(delta)
    assert accounting.default_delta(agents) <= min(1e-5, 1 / (10 * agents))


# --- 8. account first, release second ---------------------------------------------------------


class Killed(RuntimeError):
    """The server dies in the window between aggregating a round and its checkpoint."""


def test_a_round_released_again_after_a_crash_is_accounted_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    releases: list[int] = []
    aggregate = PrivateRounds.aggregate

    def counted(self: PrivateRounds, round_number: int, *args: Any, **kwargs: Any) -> Any:
        theta = aggregate(self, round_number, *args, **kwargs)
        releases.append(round_number)  # θ̃ of this round exists: it goes out next
        return theta

    monkeypatch.setattr(PrivateRounds, "aggregate", counted)
    evaluate = InProcessPool.evaluate

    def dies_at_round_3(self: InProcessPool, round_index: int, *args: Any) -> Any:
        if round_index == 3 and len(releases) == 3:
            raise Killed("killed after aggregating round 3, before its checkpoint")
        return evaluate(self, round_index, *args)

    monkeypatch.setattr(InProcessPool, "evaluate", dies_at_round_3)
    out = tmp_path / "run"
    dp_run = ["agents=homogeneous4", "privacy=dp", "privacy.noise_multiplier=3", "eval.every=1"]
    dp_run += ["eval.episodes=1", "rounds=5"]
    with pytest.raises(Killed):
        api.run(overrides=dp_run, out_dir=out)
    assert latest_valid_checkpoint(out / "checkpoints").round == 2
    resumed = api.run(overrides=[*dp_run, "resume=true"], out_dir=out)
    assert releases == [1, 2, 3, 3, 4, 5]  # θ̃ of round 3 went out twice, with fresh noise
    last = resumed.records[-1]
    assert last["privacy"]["rounds_accounted"] == len(releases)
    sampling = sampling_of(resumed.config)
    assert last["epsilon"] == pytest.approx(
        accounting.epsilon(3.0, sampling, len(releases), last["delta"])
    )


# --- 9. noise from a CSPRNG, a sum of Gaussians -----------------------------------------------


def test_secure_noise_is_the_operating_systems_bits_as_a_sum_of_gaussians(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    source = dp.noise_stream(None, 1, None)
    assert isinstance(source, dp.SecureNoise)
    draws = dp.gaussian(source, 100_000, 2.0)
    # the sample std's relative standard error is 1/√(2n) = 0.22 %; 5 of them
    assert float(np.std(draws)) == pytest.approx(2.0, rel=5 / math.sqrt(2 * draws.size))
    assert abs(float(np.mean(draws))) < 5 * 2.0 / math.sqrt(draws.size)
    assert kstest(draws / 2.0, "norm").pvalue > 1e-3
    # its bits are os.urandom's: with them fixed, each draw is the sum of four Box–Muller
    # normals (both of each pair used, in order) over √4, computed here from the same bytes
    fixed = np.random.default_rng(7).bytes(8 * 4 * 3)
    monkeypatch.setattr(os, "urandom", lambda n: fixed[:n])
    drawn = dp.gaussian(dp.SecureNoise(), 3, 1.0)
    words = np.frombuffer(fixed, dtype=np.uint64) >> np.uint64(11)
    uniform = words.astype(np.float64) * 2.0**-53
    radius = np.sqrt(-2 * np.log1p(-uniform[0::2]))
    angle = 2 * np.pi * uniform[1::2]
    normals = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1).ravel()
    assert drawn == pytest.approx(normals.reshape(4, 3).sum(axis=0) / 2, rel=1e-12)


def test_a_dp_run_draws_its_noise_securely_unless_seeded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[int] = []
    normal = dp.SecureNoise.normal

    def counted(self: dp.SecureNoise, loc: float, scale: float, size: int) -> np.ndarray:
        calls.append(size)
        return normal(self, loc, scale, size)

    monkeypatch.setattr(dp.SecureNoise, "normal", counted)
    plain = ["agents=homogeneous4", "rounds=2", "eval.every=2", "eval.episodes=1", "privacy=dp"]
    api.run(overrides=[*plain, "privacy.noise_multiplier=1"])
    assert calls  # the server's central noise, every round
    calls.clear()
    api.run(overrides=[*plain, "privacy.noise_multiplier=1", "privacy.noise_seed=2"])
    assert not calls
    with pytest.raises(ConfigError, match="noise_seed") as refused:
        api.resolve_config(
            overrides=[
                *plain,
                "privacy.epsilon=1",
                "privacy.secure_noise=true",
                "privacy.noise_seed=2",
            ]
        )
    assert refused.value.key == "privacy.secure_noise"


def test_a_plan_that_would_name_a_secret_sample_is_refused() -> None:
    with pytest.raises(ConfigError, match="would name the sample") as refused:
        api.resolve_config(
            overrides=[
                *SAMPLED,
                "privacy=dp",
                "privacy.epsilon=4",
                "agents.plan=theorem1",
                "algo.bound_estimates=true",
            ]
        )
    assert refused.value.key == "agents.plan"
