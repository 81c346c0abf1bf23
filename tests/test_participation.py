"""Participation (``strategy.participation``): who trains each round.

The seeded uniform sampler draws C distinct agents from (seed, round) alone: the same sets for
the same seed, other sets for another seed, every pair equally often; a resumed run selects
what an uninterrupted one does and ends with its θ̃; the distributed runtime selects and ends
exactly as the in-process one. A trace keeps an offline agent out of its rounds. Mistakes are
one line naming the key.
"""

from __future__ import annotations

import itertools
import json
import os
import statistics
import subprocess
from collections import Counter
from pathlib import Path

import pytest
import torch
from procs import BIN, QUIET, processes, start

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.settings.strategy import ParticipationConfig
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.checkpoint import latest_valid_checkpoint
from fedhpg.server.commands import api
from fedhpg.server.participation import Participation
from fedhpg.server.strategies import validate_strategy

EXAMPLE_TRACE = Path(__file__).parent.parent / "docs" / "availability-trace.csv"
SMALL = [  # GridWorld, tiny budgets: a round is a few milliseconds
    "agents=homogeneous4",
    "agents.budget.batch_size=[4]",
    "agents.budget.local_iters=[1]",
    "eval.every=100",
    "eval.episodes=2",
]
UNIFORM = [*SMALL, "agents.num_agents=5", "strategy.participation.mode=uniform"]
UNIFORM += ["strategy.participation.per_round=2"]


def uniform(seed: int, num_agents: int = 5, per_round: int = 2) -> Participation:
    config = ParticipationConfig(mode="uniform", per_round=per_round)
    return Participation(config, seed=seed, num_agents=num_agents)


def chi_square_quantile(df: int, tail: float) -> float:
    """Upper ``tail`` quantile of χ²(df), Wilson–Hilferty (within ~1% here; no scipy)."""
    z = statistics.NormalDist().inv_cdf(1.0 - tail)
    return df * (1.0 - 2.0 / (9 * df) + z * (2.0 / (9 * df)) ** 0.5) ** 3


def test_uniform_draws_c_distinct_agents_from_the_seed_and_round_alone() -> None:
    rounds = range(1, 2001)
    drawn = [uniform(seed=3).select(t) for t in rounds]
    assert all(len(set(s)) == 2 and s == sorted(s) and set(s) <= set(range(5)) for s in drawn)
    assert drawn == [uniform(seed=3).select(t) for t in rounds], "same seed, same sets"
    # another seed: a round repeats the set with probability 1/10, so ~90% of rounds differ
    # (σ of that fraction over 2000 rounds ≈ 0.007; 0.8 is far below)
    other = [uniform(seed=4).select(t) for t in rounds]
    assert sum(a != b for a, b in zip(drawn, other, strict=True)) / len(drawn) > 0.8
    # uniform over the 10 pairs: Pearson's χ² with 9 degrees of freedom, one-in-10⁴ bound
    pairs = list(itertools.combinations(range(5), 2))
    counts = Counter(tuple(s) for s in drawn)
    expected = len(drawn) / len(pairs)
    chi_square = sum((counts[p] - expected) ** 2 / expected for p in pairs)
    assert chi_square < chi_square_quantile(len(pairs) - 1, 1e-4), (chi_square, counts)
    # C = K is every agent; mode 'all' is every agent
    assert uniform(seed=0, per_round=5).select(7) == [0, 1, 2, 3, 4]
    assert Participation(ParticipationConfig(), seed=0, num_agents=3).select(1) == [0, 1, 2]


def test_the_chi_square_check_rejects_a_biased_sampler() -> None:
    """The bound above can fail: a sampler that favours agent 0 exceeds it."""
    drawn = [uniform(seed=3).select(t) for t in range(1, 2001)]
    biased = [[0, s[1]] if t % 3 == 0 else s for t, s in enumerate(drawn)]
    pairs = list(itertools.combinations(range(5), 2))
    counts = Counter(tuple(s) for s in biased)
    expected = len(biased) / len(pairs)
    chi_square = sum((counts[p] - expected) ** 2 / expected for p in pairs)
    assert chi_square > chi_square_quantile(len(pairs) - 1, 1e-4)


def test_only_the_selected_agents_train_and_metrics_record_them(tmp_path: Path) -> None:
    result = api.run(overrides=[*UNIFORM, "rounds=4", "seed=2"], out_dir=tmp_path / "run")
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    assert records == result.records
    for record in records:
        assert record["selected"] == uniform(seed=2).select(record["round"])
        assert [a["index"] for a in record["agents"]] == record["selected"]


def test_a_resumed_run_selects_the_same_agents_and_ends_with_the_same_theta(
    tmp_path: Path,
) -> None:
    keys = [*UNIFORM, "seed=6"]
    uninterrupted = api.run(overrides=[*keys, "rounds=6"])
    out_dir = tmp_path / "run"
    api.run(overrides=[*keys, "rounds=3"], out_dir=out_dir)  # stopped after round 3
    resumed = api.run(overrides=[*keys, "rounds=6", "resume=true"], out_dir=out_dir)
    assert [r["round"] for r in resumed.records] == list(range(1, 7))
    selected = [r["selected"] for r in resumed.records]
    assert selected == [r["selected"] for r in uninterrupted.records]
    assert len({tuple(s) for s in selected[3:]}) > 1, "the rounds after the resume differ"
    assert torch.equal(resumed.theta, uninterrupted.theta)


def test_an_agent_offline_in_the_trace_gets_no_work_in_those_rounds() -> None:
    keys = [*SMALL, "rounds=5", "seed=1", "strategy.participation.mode=trace"]
    keys.append(f"strategy.participation.trace={EXAMPLE_TRACE}")
    records = api.run(overrides=keys).records
    expected = [[0, 1, 2, 3], [0, 2, 3], [0, 2, 3], [0, 1, 2, 3], [0, 1, 2]]
    assert [r["selected"] for r in records] == expected
    assert [[a["index"] for a in r["agents"]] for r in records] == expected
    assert [r["updates"] for r in records] == [4, 3, 3, 4, 3]


def test_a_plugin_strategy_selects_among_the_participating_agents() -> None:
    """Participation first, then the strategy's own select (toy_alternate: the even-indexed
    agents in even rounds)."""
    keys = [*SMALL, "rounds=4", "seed=1", "plugins=[fedhpg_toy_plugin]"]
    keys += ["strategy.name=toy_alternate", "strategy.participation.mode=trace"]
    keys.append(f"strategy.participation.trace={EXAMPLE_TRACE}")
    records = api.run(overrides=keys).records
    assert [r["selected"] for r in records] == [[0, 1, 2, 3], [0, 2], [0, 2, 3], [0, 2]]


def test_distributed_uniform_sampling_equals_in_process_bit_for_bit(tmp_path: Path) -> None:
    # a command line as typed: agents.num_agents once (UNIFORM has 5)
    keys = [k.replace("num_agents=5", "num_agents=4") for k in UNIFORM] + ["rounds=4", "seed=9"]
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*keys, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'h'}"],
            cwd=tmp_path,
        )
        _, stderr = launcher.communicate(timeout=120)
    assert launcher.returncode == 0, stderr[-3000:]
    distributed = [
        json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()
    ]
    in_process = api.run(overrides=keys)
    assert [r["selected"] for r in distributed] == [r["selected"] for r in in_process.records]
    assert [[a["index"] for a in r["agents"]] for r in distributed] == [
        r["selected"] for r in distributed
    ]
    checkpoint = latest_valid_checkpoint(out_dir / "checkpoints")
    assert checkpoint is not None and checkpoint.round == 4
    assert torch.equal(checkpoint.theta, in_process.theta)


BAD_INPUTS = [
    (["strategy.participation.mode=some"], "strategy.participation.mode: got 'some', allowed"),
    (["strategy.participation.mode=uniform"], "strategy.participation.per_round: mode 'uniform'"),
    (
        ["strategy.participation.mode=uniform", "strategy.participation.per_round=0"],
        "strategy.participation.per_round: got 0, must be an integer >= 1",
    ),
    (
        ["strategy.participation.mode=uniform", "strategy.participation.per_round=5"],
        "strategy.participation.per_round: got 5, must be <= agents.num_agents=4",
    ),
    (["strategy.participation.mode=trace"], "strategy.participation.trace: mode 'trace' needs"),
]


@pytest.mark.parametrize(("overrides", "message"), BAD_INPUTS)
def test_bad_settings_name_the_key(overrides: list[str], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        compose([*SMALL, *overrides])
    assert str(info.value).startswith(message), str(info.value)


BAD_TRACES = {
    "header": ("agent,from,to\n1,2,3\n", "line 1: the header must be agent,offline_from"),
    "row": ("agent,offline_from,offline_to\n1,2,3\n2,x,4\n", "line 3: needs three non-negative"),
    "agent": ("agent,offline_from,offline_to\n4,1,1\n", "line 2: agent 4 is not < agents.num"),
    "interval": ("agent,offline_from,offline_to\n0,3,2\n", "line 2: needs 1 <= offline_from"),
    "nobody": (
        "agent,offline_from,offline_to\n0,2,2\n1,1,3\n2,2,9\n3,2,2\n",
        "every agent is offline in round 2 of",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_TRACES))
def test_a_bad_trace_names_the_file_and_line(tmp_path: Path, case: str) -> None:
    text, message = BAD_TRACES[case]
    trace = tmp_path / "trace.csv"
    trace.write_text(text)
    run = compose(
        [*SMALL, "strategy.participation.mode=trace", f"++strategy.participation.trace={trace}"]
    )
    with pytest.raises(ConfigError) as info:
        validate_strategy(run)
    assert info.value.key == "strategy.participation.trace"
    assert message in str(info.value), str(info.value)
    assert str(trace) in str(info.value)


def test_a_missing_trace_through_fedhpg_run_is_one_line_exit_2_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    args = ["strategy.participation.mode=trace", "strategy.participation.trace=nowhere.csv"]
    done = subprocess.run(
        [str(BIN / "fedhpg-run"), *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, **QUIET},
    )
    assert done.returncode == 2
    assert done.stderr.strip() == "error: strategy.participation.trace: no such file: nowhere.csv"
    assert list(tmp_path.iterdir()) == []


def test_defaults_select_every_agent() -> None:
    records: list = []
    run_in_process(compose([*SMALL, "rounds=2"]), on_round=[lambda r, _: records.append(r)])
    assert [r.selected for r in records] == [[0, 1, 2, 3]] * 2


def test_a_resume_keeps_the_participation(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    api.run(overrides=[*UNIFORM, "rounds=2"], out_dir=out_dir)
    changed = [*UNIFORM, "rounds=3", "resume=true", "strategy.participation.per_round=3"]
    with pytest.raises(ConfigError) as info:
        api.run(overrides=changed, out_dir=out_dir)
    assert info.value.key == "strategy.participation.per_round"
