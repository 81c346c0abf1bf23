"""Config groups and the paper's presets: they compose, sweep over seeds, and plot."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from procs import BIN, processes, start

from fedhpg.common.configuration.config import to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.runtime.cli import compose
from fedhpg.server.commands.api import resolve_config
from fedhpg.server.commands.plot import main as plot_main

CONF = Path(__file__).parents[1] / "conf"
PRESETS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
GROUPS = {
    g: sorted(p.stem for p in (CONF / g).glob("*.yaml"))
    for g in ("algo", "env", "agents", "strategy", "attack")
}


def test_the_paper_presets_exist() -> None:
    assert {"fig1_batch_size", "fig2_local_iters", "fig3_vr_inner_loops"} <= set(PRESETS)


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_composes_and_validates(preset: str) -> None:
    run = compose([f"experiment={preset}"])
    if preset.startswith("fig"):  # the paper's Section VI: 4 GridWorld agents
        assert run.rounds == 100 and run.agents.num_agents == 4


@pytest.mark.parametrize(("group", "option"), [(g, o) for g, opts in GROUPS.items() for o in opts])
def test_every_group_option_composes(group: str, option: str) -> None:
    needs = {("env", "gym"): ["env.id=CartPole-v1"]}  # env=gym runs the id it is given
    compose([f"{group}={option}", *needs.get((group, option), [])])


@pytest.mark.parametrize(
    ("override", "key", "hint"),
    [
        ("algo=nope", "algo", "allowed: fedhpg, fedhpgvr"),
        ("experiment=fig9", "experiment", "allowed: fig1_batch_size"),
        ("agents.budget.batch_size=[0]", "agents.budget.batch_size[0]", "integer >= 1"),
        ("algo.step_size=fast", "algo.step_size", "could not be converted to Float"),
    ],
)
def test_bad_overrides_name_the_key(override: str, key: str, hint: str) -> None:
    with pytest.raises(ConfigError, match=hint) as info:
        compose([override])
    assert info.value.key == key


def test_fedhpg_run_rejects_an_unknown_group_option_with_one_line(tmp_path: Path) -> None:
    result = subprocess.run(
        [str(BIN / "fedhpg-run"), "algo=nope"], capture_output=True, text=True, timeout=60,
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 2
    expected = "error: algo: no such option 'nope'; allowed: fedhpg, fedhpgvr, fedpgbr"
    assert result.stderr.strip() == expected


@pytest.mark.alongside  # fedhpg-run on a free port with the defaults' waits, checked by its outputs
def test_tiny_multirun_then_plot(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            ["-m", "experiment=fig2_local_iters", "seed=0,1", "rounds=2", "eval.every=1",
             f"hydra.sweep.dir={sweep}"],
            cwd=tmp_path,
        )  # fmt: skip
        _, stderr = launcher.communicate(timeout=180)
    assert launcher.returncode == 0, stderr[-2000:]
    metrics = sorted(sweep.glob("*/metrics.jsonl"))
    assert len(metrics) == 2 and all(len(m.read_text().splitlines()) == 2 for m in metrics)
    out = tmp_path / "curves.png"
    for axis in ("rounds", "trajectories", "emulated"):
        assert plot_main([str(sweep), "--x", axis, "--out", str(out)]) == 0
        assert out.stat().st_size > 1000 and out.with_suffix(".svg").exists()
    assert plot_main([str(tmp_path / "missing")]) == 2


# -- the K=10 LunarLander and HalfCheetah presets are the benchmarked set-ups -----------------

K10_PRESETS = [
    # (preset, family, B, algo.normalize, evaluated every so many trajectories per agent)
    ("k10_lunarlander", "lunarlander", 32, "none", 128),
    ("k10_lunarlander_tuned", "lunarlander", 16, "episode", 128),
    ("k10_halfcheetah", "halfcheetah", 48, "none", 192),
    ("k10_halfcheetah_tuned", "halfcheetah", 16, "none", 192),
]


@pytest.mark.parametrize(("preset", "family", "batch_size", "normalize", "cadence"), K10_PRESETS)
def test_k10_presets_are_the_benchmarked_set_up(
    preset: str, family: str, batch_size: int, normalize: str, cadence: int
) -> None:
    """The keys of benchmarks/learning_long.py and benchmarks/tuned_presets.py (BENCHMARKS.md's
    figures), composed and validated as a run is."""
    run = resolve_config(overrides=[f"experiment={preset}"])
    assert (run.env.family, run.env.level, run.env.gamma) == (family, 0.0, 1.0)
    assert run.agents.num_agents == 10
    assert run.agents.budget["batch_size"] == [batch_size]
    assert run.agents.budget["local_iters"] == [1]
    assert run.policy.hidden == [64, 64]
    assert (run.algo.name, run.algo.estimator, run.algo.baseline) == ("fedhpg", "gpomdp", "mean")
    assert (run.algo.reward_to_go, run.algo.normalize) == ("from_start", normalize)
    assert (run.algo.optimizer, run.algo.step_size) == ("sgd", 1.0)
    assert run.strategy.name == "fedadam" and run.strategy.params["step_size"] == 0.003
    # one greedy episode per agent at the same trajectories per agent, whatever B is
    assert (run.eval.episodes, run.eval.greedy, run.eval.horizon) == (1, True, 1000)
    assert run.eval.every * batch_size == cadence


@pytest.mark.parametrize("task", ["lunarlander", "halfcheetah"])
def test_tuned_k10_preset_is_the_benchmarked_setting(task: str) -> None:
    """benchmarks/tuned_presets.py measures the tuned preset as the paper-faithful one with B,
    the estimator's normalisation and the evaluation interval changed: the two compose to the
    same run."""
    tuned = compose([f"experiment=k10_{task}_tuned"])
    base = compose(
        [
            f"experiment=k10_{task}",
            f"agents.budget.batch_size={tuned.agents.budget['batch_size']}",
            f"algo.normalize={tuned.algo.normalize}",
            f"eval.every={tuned.eval.every}",
            f"rounds={tuned.rounds}",
        ]
    )
    assert to_dict(tuned) == to_dict(base)
