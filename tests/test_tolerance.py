"""Robust rules hold their stated tolerance per aggregated set, or the run is refused.

A robust rule survives a number of arbitrary rows among the m rows it aggregates, not among
the K agents: ``median`` ⌈m/2⌉ − 1, ``trimmed_mean`` ⌊βm⌋. The bound tested here is the
rule's own: with every attacker inside the tolerance, each coordinate of θ̃_r − θ̃_{r−1}
lies between the honest rows' changes, and an honest change is at most τ·α·c in norm (plain
steps of size α, the gradient clipped to c, τ of them). Attackers flip and blow up their
change a thousandfold (``sign_flip``, scale 1e3), so a rule that let one through would move θ̃
by orders of magnitude more than the bound.
"""

from __future__ import annotations

import subprocess

import pytest
import torch
from procs import BIN

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.runtime.cli import compose
from fedhpg.server.commands import api
from fedhpg.server.strategies import make_strategy, validate_strategy
from fedhpg.server.tolerance import smallest_set

STEP, CLIP, ROUNDS = 0.1, 1.0, 8
BOUND = ROUNDS * STEP * CLIP  # τ = 1: θ̃ moves at most α·c a round under an honest rule
ATTACK = ["attack=sign_flip", "attack.sign_flip_scale=1000"]


def _keys(agents: int, *extra: str) -> list[str]:
    return [
        f"rounds={ROUNDS}", "seed=11", f"agents.num_agents={agents}",
        "agents.budget.batch_size=[4]", "agents.budget.local_iters=[1]", "agents.speeds=[1]",
        "agents.step_delays_s=[0]", "agents.clock=counted", f"algo.step_size={STEP}",
        f"algo.grad_clip={CLIP}", f"eval.every={ROUNDS}", "eval.episodes=2",
        "server.tensorboard=false", *extra,
    ]  # fmt: skip


def _moved(result: api.RunResult, start: torch.Tensor) -> float:
    return float((result.theta - start).abs().max())


def _start(keys: list[str]) -> torch.Tensor:
    return api.run(overrides=[*keys, "rounds=1", "algo.step_size=1e-30"]).theta


@pytest.mark.parametrize(
    ("rule", "rows", "tolerates"),
    [("median", 1, 0), ("median", 2, 0), ("median", 3, 1), ("median", 10, 4)]
    + [("trimmed_mean", m, t) for m, t in ((4, 0), (5, 1), (10, 2), (14, 2), (15, 3))],
)
def test_each_rule_states_its_tolerance_for_the_rows_it_aggregates(
    rule: str, rows: int, tolerates: int
) -> None:
    strategy = make_strategy(compose([f"strategy={rule}"]).strategy)
    assert strategy.tolerance(rows) == tolerates
    assert make_strategy(compose(["strategy=mean"]).strategy).tolerance(rows) is None
    inner = compose(["strategy=fedadam", f"strategy.params.inner={rule}"]).strategy
    assert make_strategy(inner).tolerance(rows) == tolerates


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (  # ⌊0.2 · 4⌋ = 0 rows trimmed: one attacker moved θ̃ by 62.5 before
            [
                "strategy=trimmed_mean",
                "strategy.participation.mode=uniform",
                "strategy.participation.per_round=4",
                "attack.agents=[0]",
            ],
            "strategy=trimmed_mean tolerates 0 arbitrary update(s) in a set of 4 "
            "(strategy.participation.per_round=4), fewer than 1 (attack.agents lists 1",
        ),
        (  # both attackers drawn into a set of 3: off by 100.8 before
            [
                "strategy=median",
                "strategy.participation.mode=uniform",
                "strategy.participation.per_round=3",
                "attack.agents=[0,1]",
            ],
            "strategy=median tolerates 1 arbitrary update(s) in a set of 3",
        ),
        (
            ["strategy=median", "server.round_policy=deadline", "server.min_agents=2"],
            "in a set of 2 (server.round_policy=deadline with server.min_agents=2), fewer than 3 "
            "(attack.agents lists 3",
        ),
        (
            ["strategy=median", "strategy.tolerate=5"],
            "tolerates 4 arbitrary update(s) in a set of 10 (every one of "
            "agents.num_agents=10), fewer than 5 (strategy.tolerate=5)",
        ),
    ],
)
def test_a_rule_that_cannot_hold_its_tolerance_is_refused(
    overrides: list[str], message: str
) -> None:
    run = compose(_keys(10, *ATTACK, *overrides))
    with pytest.raises(ConfigError, match="strategy") as info:
        validate_strategy(run)
    assert message in str(info.value)
    assert "strategy.tolerance_check=warn" in str(info.value)


def test_the_refusal_is_one_line_before_anything_starts(tmp_path) -> None:
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), *_keys(10, *ATTACK, "strategy=trimmed_mean",
         "strategy.participation.mode=uniform", "strategy.participation.per_round=4",
         "attack.agents=[0]")],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: strategy: strategy=trimmed_mean")
    assert not (tmp_path / "outputs").exists()


def test_a_run_within_the_tolerance_stays_within_the_bound_and_records_it() -> None:
    """β = 0.25 over 4 of 10 sampled trims one row a side: one attacker, in every set it is
    drawn into, is trimmed; each round records the rows it aggregated and their tolerance."""
    keys = _keys(
        10, *ATTACK, "attack.agents=[0]", "strategy=trimmed_mean",
        "strategy.params.trim_fraction=0.25", "strategy.participation.mode=uniform",
        "strategy.participation.per_round=4",
    )  # fmt: skip
    result = api.run(overrides=keys)
    assert any(0 in r["selected"] for r in result.records), "the attacker was never drawn"
    assert all(r["strategy"] == {"aggregated": 4, "tolerates": 1} for r in result.records)
    assert _moved(result, _start(keys)) <= BOUND


def test_warn_runs_an_intolerant_rule_and_says_so(caplog: pytest.LogCaptureFixture) -> None:
    keys = _keys(
        10, *ATTACK, "attack.agents=[0,1]", "strategy=median",
        "strategy.participation.mode=uniform", "strategy.participation.per_round=3",
        "strategy.tolerance_check=warn",
    )  # fmt: skip
    result = api.run(overrides=keys)
    assert "strategy=median tolerates 1 arbitrary update(s) in a set of 3" in caplog.text
    assert all(r["strategy"] == {"aggregated": 3, "tolerates": 1} for r in result.records)


@pytest.mark.parametrize("rule", ["median", "trimmed_mean"])
def test_buffered_rounds_let_no_fast_attacker_crowd_the_set(rule: str) -> None:
    """M = 3 of K = 5 with the two attackers 8× faster than the rest: they arrive first and
    fill two thirds of every buffer (θ̃ was off by 448 and 677 under median before). A robust
    rule aggregates one row per agent, its latest change (θ̃ itself until it has one), so
    the attackers are 2 rows of 5, within median's 2 and trimmed_mean's ⌊0.4 · 5⌋ = 2."""
    keys = _keys(
        5, *ATTACK, "attack.agents=[0,1]", f"strategy={rule}",
        "strategy.params.trim_fraction=0.4" if rule == "trimmed_mean" else "seed=11",
        "server.round_policy=buffered", "server.buffer_size=3", "agents.speeds=[8,8,1,1,1]",
    )  # fmt: skip
    assert smallest_set(compose(keys))[0] == 5
    result = api.run(overrides=keys)
    counts = [sum(a["id"] in ("agent-0", "agent-1") for a in r["agents"]) for r in result.records]
    assert sum(counts) >= ROUNDS, f"the attackers were not in the buffers: {counts}"
    assert all(r["strategy"] == {"aggregated": 5, "tolerates": 2} for r in result.records)
    assert _moved(result, _start(keys)) <= BOUND


def test_buffered_robust_rule_with_every_agent_in_the_buffer_is_wait_all() -> None:
    """M = K: every row is fresh, so the robust set is the buffer and the run is wait_all's."""
    keys = _keys(5, "strategy=median", "agents.speeds=[8,8,1,1,1]")
    buffered = api.run(overrides=[*keys, "server.round_policy=buffered", "server.buffer_size=5"])
    assert torch.equal(buffered.theta, api.run(overrides=keys).theta)
