"""privacy= in whole runs, in process: ε in every record, TensorBoard and summary.json; the
budget that stops a run before it is exceeded, across a resume; secure aggregation's θ̃
against the plain average; the combinations refused at start, in one line."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.privacy import accounting
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api
from fedhpg.server.metrics import read_metrics
from fedhpg.server.privacy import BudgetExhausted, sampling_of

BIN = Path(sys.prefix) / "bin"
SMALL = ["rounds=4", "eval.every=2", "eval.episodes=2", "seed=2"]
SAMPLED = [
    "agents=homogeneous10",
    "agents.budget.batch_size=[4]",
    "strategy.participation.mode=uniform",
    "strategy.participation.per_round=4",
]


def test_dp_records_epsilon_every_round_as_the_accountant_says(tmp_path: Path) -> None:
    result = api.run(
        overrides=[*SMALL, *SAMPLED, "privacy=dp", "privacy.epsilon=3", "privacy.clip=0.5"],
        out_dir=tmp_path / "run",
    )
    run = result.config
    sigma = result.records[0]["privacy"]["noise_multiplier"]
    delta = 1e-5  # the default: min(1/(10K), 1e-5)
    sampling = sampling_of(run)
    assert sampling.kind == "fixed" and sampling.sample == 4
    for t, record in enumerate(result.records, start=1):
        assert record["delta"] == pytest.approx(delta)
        assert record["epsilon"] == pytest.approx(accounting.epsilon(sigma, sampling, t, delta))
        assert record["agents"] == []  # a secret sample: no agent's row
    # σ was calibrated to spend the budget in exactly the run's rounds
    assert result.records[-1]["epsilon"] == pytest.approx(3.0, rel=1e-3)
    assert result.records[-1]["epsilon"] <= 3.0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())["privacy"]
    assert summary["epsilon"] == result.records[-1]["epsilon"]
    assert summary["neighbouring"] == "replace one agent"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    board = EventAccumulator(str(tmp_path / "run" / "tensorboard"))
    board.Reload()
    epsilons = [e.value for e in board.Scalars("privacy/epsilon")]
    assert epsilons == pytest.approx([r["epsilon"] for r in result.records], rel=1e-6)


def test_a_run_stops_before_it_would_exceed_its_budget(tmp_path: Path) -> None:
    out = tmp_path / "run"
    dp = [*SAMPLED, "privacy=dp", "privacy.epsilon=2", "eval.every=2", "eval.episodes=1"]
    first = api.run(overrides=[*dp, "rounds=3"], out_dir=out)
    sigma = first.records[-1]["privacy"]["noise_multiplier"]
    theta = latest_valid_checkpoint(out / "checkpoints").theta
    # more rounds on resume: σ stays the checkpoint's, so round 4 would pass ε = 2
    with pytest.raises(BudgetExhausted, match=r"privacy.epsilon: round 4 would spend ε = .* > "):
        api.run(overrides=[*dp, "rounds=6", "resume=true"], out_dir=out)
    kept = latest_valid_checkpoint(out / "checkpoints")
    assert kept.round == 3 and torch.equal(kept.theta, theta)
    assert kept.state["privacy"]["sigma"] == sigma
    assert len(read_metrics(out / "metrics.jsonl")) == 3


def test_a_given_noise_multiplier_stops_at_the_round_that_would_pass_the_cap(
    tmp_path: Path,
) -> None:
    # σ given and ε a cap: the run goes on while the accountant stays within it, and stops
    # before the first round that would not (here the third: the cap is half-way between the
    # ε of two rounds and of three)
    sampling = accounting.Sampling(kind="fixed", population=10, sample=4)
    two, three = (accounting.epsilon(0.9, sampling, t, 1e-5) for t in (2, 3))
    cap = (two + three) / 2
    out = tmp_path / "run"
    dp = [*SAMPLED, "privacy=dp", "privacy.noise_multiplier=0.9", f"privacy.epsilon={cap}"]
    with pytest.raises(BudgetExhausted, match=r"round 3 would spend ε = .*the run stops here"):
        api.run(overrides=[*dp, "rounds=20", "eval.every=20", "eval.episodes=1"], out_dir=out)
    records = read_metrics(out / "metrics.jsonl")
    assert [r["round"] for r in records] == [1, 2]
    assert records[-1]["epsilon"] == pytest.approx(two) and two <= cap
    assert latest_valid_checkpoint(out / "checkpoints").round == 2


def test_resume_keeps_the_accountants_state(tmp_path: Path) -> None:
    out = tmp_path / "run"
    dp = [*SAMPLED, "privacy=dp", "privacy.noise_multiplier=1.5", "eval.every=2"]
    api.run(overrides=[*dp, "rounds=2", "eval.episodes=1"], out_dir=out)
    resumed = api.run(overrides=[*dp, "rounds=4", "eval.episodes=1", "resume=true"], out_dir=out)
    sampling = sampling_of(resumed.config)
    records = resumed.records
    assert [r["round"] for r in records] == [1, 2, 3, 4]
    assert records[-1]["privacy"]["rounds_accounted"] == 4
    assert records[-1]["epsilon"] == pytest.approx(accounting.epsilon(1.5, sampling, 4, 1e-5))


def test_secure_aggregation_gives_the_plain_average() -> None:
    plain = api.run(overrides=[*SMALL, *SAMPLED])
    secure = api.run(overrides=[*SMALL, *SAMPLED, "privacy=secagg"])
    # the sum is exact in fixed point; what differs is float32's rounding of the mean
    assert torch.allclose(secure.theta, plain.theta, rtol=0, atol=1e-6)
    assert all(r["privacy"] == {"mode": "secagg", "inputs": 4} for r in secure.records)
    weighted = ["strategy=weighted", "agents.budget.batch_size=[2,3,4,5,6,7,8,9,10,11]"]
    plain = api.run(overrides=[*SMALL, *SAMPLED, *weighted])
    secure = api.run(overrides=[*SMALL, *SAMPLED, *weighted, "privacy=secagg"])
    assert torch.allclose(secure.theta, plain.theta, rtol=0, atol=1e-6)


def test_distributed_noise_and_adaptive_clipping() -> None:
    overrides = [*SMALL, *SAMPLED, "privacy.noise_multiplier=1.0", "privacy.noise_seed=5"]
    clipped = ["privacy.adaptive_clip=true", "privacy.clip=1e-4", "privacy.clip_rate=1.0"]
    central = api.run(overrides=[*overrides, "privacy=dp", *clipped])
    clips = [r["privacy"]["clip"] for r in central.records]
    # every update is longer than 1e-4: the clip grows each round (by about e^0.5)
    assert all(b > a * 1.2 for a, b in itertools.pairwise(clips))
    plain = api.run(overrides=[*SMALL, *SAMPLED, "privacy=secagg"])
    noisy = api.run(overrides=[*overrides, "privacy=dp_secagg"])
    again = api.run(overrides=[*overrides, "privacy=dp_secagg"])
    assert torch.equal(noisy.theta, again.theta)  # seeded noise: reproducible
    assert not torch.allclose(noisy.theta, plain.theta, atol=1e-3)
    assert noisy.records[-1]["epsilon"] > 0


def test_privacy_on_the_torch_engine_and_its_device_cartpole() -> None:
    # the engine that runs on a GPU with algo.device=cuda, here on the CPU: its θ_k come back
    # as CPU arrays, where clipping, noise and masks are computed
    overrides = [
        "env=cartpole",
        "strategy=mean",  # not the preset's fedadam, whose first steps magnify float rounding
        "~strategy.params.step_size",
        "algo.step_size=0.01",
        "algo.engine=torch",
        "agents=homogeneous4",
        "agents.budget.batch_size=[2]",
        "rounds=2",
        "eval.every=2",
        "eval.episodes=1",
    ]
    plain = api.run(overrides=overrides)
    secure = api.run(overrides=[*overrides, "privacy=secagg"])
    assert torch.allclose(secure.theta, plain.theta, rtol=0, atol=1e-6)
    noisy = api.run(overrides=[*overrides, "privacy=dp_secagg", "privacy.noise_multiplier=1"])
    assert noisy.records[-1]["privacy"]["inputs"] == 4 and noisy.records[-1]["epsilon"] > 0


@pytest.mark.parametrize(
    ("overrides", "key", "words"),
    [
        (["strategy=median", "privacy=secagg"], "privacy.mode", "strategy=median needs each"),
        (
            [
                "strategy=trimmed_mean",
                "strategy.tolerance_check=warn",
                "privacy=dp",
                "privacy.epsilon=1",
            ],
            "privacy.mode",
            "trimmed_mean needs",
        ),
        (["algo=fedpgbr", "privacy=secagg"], "privacy.mode", "strategy=fedpgbr"),
        (["strategy=weighted", "privacy=dp", "privacy.epsilon=1"], "privacy.mode", "unbounded"),
        (["privacy=dp"], "privacy.epsilon", "needs a budget"),
        (
            ["privacy=secagg", "server.round_policy=buffered"],
            "server.round_policy",
            "synchronous rounds",
        ),
        (["privacy=secagg", "privacy.secagg.threshold=1"], "privacy.secagg.threshold", "(0, 1)"),
        # ten agents, 9 neighbours each: t = 5 lets one colluder and split unmasking requests
        # rebuild both secrets of an agent (accepted before); t = 6 is the least that holds
        (
            ["privacy=secagg", "agents=homogeneous10", "privacy.secagg.threshold=0.5"],
            "privacy.secagg.threshold",
            "t = 6 of k = 9 would",
        ),
        (
            ["privacy=secagg", "agents=homogeneous10", "privacy.secagg.neighbours=4"],
            "privacy.secagg.neighbours",
            "cannot both hide every input",
        ),
        (["privacy=secagg", "privacy.secagg.corruption=0.5"], "privacy.secagg.corruption", "0.5"),
    ],
)
def test_incompatible_combinations_are_refused(overrides: list[str], key: str, words: str) -> None:
    with pytest.raises(ConfigError, match=words) as refused:
        api.resolve_config(overrides=overrides)
    assert refused.value.key == key


def test_the_command_line_refuses_in_one_line(tmp_path: Path) -> None:
    done = subprocess.run(
        [str(BIN / "fedhpg-run"), "strategy=median", "privacy=secagg"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "error: privacy.mode: got 'secagg'; strategy=median needs each agent's update alone, "
        "which privacy hides or changes: use strategy=mean, weighted, or fedadam over either"
    ]
    assert list(tmp_path.iterdir()) == []


BLOCK_PRIVACY_EXTRA = """
import importlib.abc, sys
class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in ("cryptography", "dp_accounting"):
            raise ImportError(f"No module named {name!r}")
sys.meta_path.insert(0, Missing())
import fedhpg.agent.main, fedhpg.server.commands.launcher, fedhpg.server.commands.server
from fedhpg.common.configuration.config import ConfigError
from fedhpg.common.runtime.cli import compose
from fedhpg.server.strategies import validate_strategy
from fedhpg.server.assembly import _check_privacy
run = compose(["privacy=secagg"])
try:
    _check_privacy(run, validate_strategy(run))
except ConfigError as error:
    print(error)
"""


def test_without_the_privacy_extra_runs_start_and_privacy_is_one_line() -> None:
    """The privacy extra (cryptography, dp-accounting) is optional: every entry point imports
    without it, and a run that asks for privacy says what to install."""
    done = subprocess.run(
        [sys.executable, "-c", BLOCK_PRIVACY_EXTRA], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "pip install 'fedhpg[privacy]'" in done.stdout, done.stdout
