"""Config groups and the paper's presets: they compose, sweep over seeds, and plot."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from procs import BIN, processes, start

from fedhpg.common.config import ConfigError
from fedhpg.common.runtime.cli import compose
from fedhpg.server.plot import main as plot_main

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
    compose([f"{group}={option}"])


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
