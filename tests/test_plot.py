"""fedhpg-plot: readable labels, markers where points are few, a band that stays inside the
data, the IQM and its bootstrap interval against values worked out by hand, one-line errors.

The run directories are real: tiny GridWorld federations run in-process, their records
written by the server's own MetricsWriter next to the config.json the server would write.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from procs import BIN

from fedhpg.common.configuration.config import to_dict
from fedhpg.common.runtime.cli import compose
from fedhpg.server.commands.plot import (
    Run,
    draw,
    draw_band,
    figure_and_axis,
    find_runs,
    group_runs,
    main,
    relabel,
    series,
)
from fedhpg.server.commands.plot_stats import (
    aggregate,
    band_over_seeds,
    iqm,
    stratified_bootstrap_ci,
)
from fedhpg.server.metrics import MetricsWriter

TINY = ["experiment=fig1_batch_size", "eval.episodes=4", "eval.every=1"]


def _real_run(directory: Path, overrides: list[str]) -> None:
    from fedhpg.server.assembly import run_in_process

    run = compose([*TINY, *overrides])
    directory.mkdir(parents=True)
    (directory / "config.json").write_text(json.dumps(to_dict(run)))
    writer = MetricsWriter(directory / "metrics.jsonl")
    try:
        run_in_process(run, on_round=[writer])
    finally:
        writer.close()


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two settings of B × two seeds, 3 rounds each, evaluated every round; numbered as
    Hydra numbers sweep jobs (10 after 2, to check the order is not the string order)."""
    root = tmp_path_factory.mktemp("sweep")
    jobs = [(b, s) for b in ("[2,5,10,20]", "[20]") for s in (0, 1)]
    for number, (batch, seed) in zip((1, 2, 10, 11), jobs, strict=True):
        _real_run(
            root / str(number), [f"agents.budget.batch_size={batch}", f"seed={seed}", "rounds=3"]
        )
    return root


@pytest.fixture(scope="module")
def single_point(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("one") / "run"
    _real_run(directory, ["rounds=1"])
    return directory


def test_labels_name_what_differs_readably(sweep: Path) -> None:
    groups = group_runs(find_runs([sweep]))
    assert list(groups) == ["B=(2, 5, 10, 20)", "B=20"]
    assert [len(runs) for runs in groups.values()] == [2, 2]


def test_algorithm_names_and_ambiguous_keys() -> None:
    configs = [
        compose(["algo=fedhpg", "algo.step_size=0.5", "strategy=fedadam"]),
        compose(["algo=fedhpgvr", "algo.step_size=0.1", "strategy=fedadam"]),
    ]
    runs = [Run(Path(str(i)), to_dict(c), []) for i, c in enumerate(configs)]
    labels = list(group_runs(runs))
    assert labels[0].startswith("FedHPG, ") and labels[1].startswith("FedHPGVR, ")
    assert "η=0.5" in labels[0] and "η=0.1" in labels[1]
    assert "algo.name" not in labels[0] and '"' not in labels[0]


def test_label_option_by_order_and_by_group(sweep: Path) -> None:
    groups = group_runs(find_runs([sweep]))
    assert list(relabel(groups, ["mixed", "large"])) == ["mixed", "large"]
    assert list(relabel(groups, ["B=20=large batches"])) == ["B=(2, 5, 10, 20)", "large batches"]


def test_a_single_evaluation_is_drawn_as_a_marker(single_point: Path) -> None:
    (run,) = find_runs([single_point])
    x, y = series(run, "rounds", "eval_success")
    assert len(x) == 1
    figure, axis = figure_and_axis()
    line, band = draw_band(axis, "one", [(x, y)])
    assert line.get_marker() == "o" and len(line.get_xdata()) == 1
    assert band.seeds == 1 and not axis.collections, "one seed: no band"
    many = np.linspace(0, 1, 200)
    line, _ = draw_band(axis, "many", [(many, many), (many, many + 0.1)])
    assert line.get_marker() in (None, "None", ""), "a dense curve is a plain line"
    plt.close(figure)


def test_figure_says_what_the_curves_and_bands_are(sweep: Path) -> None:
    groups = group_runs(find_runs([sweep]))
    figure = draw(groups, x_axis="trajectories", metric="eval_return", title="t", stat="iqm")
    axis = figure.axes[0]
    title = axis.get_legend().get_title().get_text()
    assert title.startswith("IQM over seeds") and "95% percentile-bootstrap CI" in title
    assert [t.get_text() for t in axis.get_legend().get_texts()] == [
        "B=(2, 5, 10, 20) (2 seeds)",
        "B=20 (2 seeds)",
    ]
    assert axis.get_ylabel() == "greedy return, mean over the agents' environments"
    per_agent = draw(groups, x_axis="rounds", metric="train_return", title="t", per_agent=True)
    assert per_agent.axes[0].get_ylabel() == "training return of the agent's own batch"
    assert len(per_agent.axes[0].get_lines()) == 2 * 4, "one curve per group and agent"
    texts = [t.get_text() for t in per_agent.axes[0].get_legend().get_texts()]
    assert texts[1] == "B=(2, 5, 10, 20), agent-1: B=5 (2 seeds)"
    assert texts[5] == "B=20, agent-1 (2 seeds)", "the same B everywhere: nothing to add"
    plt.close(figure)
    plt.close(per_agent)


def test_the_band_never_leaves_the_data() -> None:
    # Success rates near 1 over 3 seeds: a Student-t interval would pass 1.
    rng = np.random.default_rng(0)
    x = np.arange(20.0)
    seeds = [(x, np.clip(1 - rng.exponential(0.1, size=20), 0, 1)) for _ in range(3)]
    values = np.stack([y for _, y in seeds])
    t_high = values.mean(0) + 4.303 * values.std(0, ddof=1) / np.sqrt(3)
    assert (t_high > 1).any(), "the case a t-interval gets wrong"
    for stat in ("mean", "median", "iqm"):
        band = band_over_seeds(seeds, stat)
        assert (band.low >= values.min(0)).all() and (band.high <= values.max(0)).all()
        assert (band.low <= band.centre).all() and (band.centre <= band.high).all()


def test_curves_are_compared_only_where_every_seed_has_data() -> None:
    short = (np.array([0.0, 1.0, 2.0]), np.array([0.0, 1.0, 2.0]))
    long = (np.array([0.0, 1.0, 2.0, 3.0]), np.array([0.0, 1.0, 2.0, 9.0]))
    assert list(band_over_seeds([long, short]).x) == [0.0, 1.0, 2.0]


def test_iqm_by_hand() -> None:
    # n=8: drop ⌊8/4⌋ = 2 from each end of 1 2 3 4 6 7 8 10 → (3+4+6+7)/4
    assert iqm(np.array([10.0, 1, 7, 2, 8, 3, 6, 4])) == 5.0
    assert iqm(np.array([10.0, 1, 4, 3, 2])) == 3.0  # n=5: drop one each side → 2 3 4
    assert iqm(np.array([0.0, 1, 5])) == 2.0  # n<4: nothing dropped, the mean
    columns = np.array([[1.0, 9.0], [2.0, 9.0], [3.0, 0.0], [100.0, 9.0]])
    assert list(iqm(columns, axis=0)) == [2.5, 9.0]


def test_bootstrap_interval_matches_the_exact_bootstrap_distribution() -> None:
    """Ten scores 0..9: a resample's mean is a sum of 10 uniform draws from them / 10; its
    exact distribution is the 10-fold convolution, and its 2.5% / 97.5% quantiles are what
    2,000 resamples must estimate (standard error ≈ 0.05 here; tolerance 0.25)."""
    scores = np.arange(10.0)
    pmf = np.ones(1)
    for _ in range(10):
        pmf = np.convolve(pmf, np.full(10, 0.1))
    cdf = np.cumsum(pmf)
    exact_low = np.searchsorted(cdf, 0.025) / 10
    exact_high = np.searchsorted(cdf, 0.975) / 10
    low, high = stratified_bootstrap_ci(scores[:, None], "mean", seed=1)
    assert abs(low - exact_low) <= 0.25 and abs(high - exact_high) <= 0.25
    # Two seeds: resample means 0, ½, 1 with probabilities ¼, ½, ¼, so the interval is [0, 1].
    low, high = stratified_bootstrap_ci(np.array([[0.0], [1.0]]), "mean")
    assert (low, high) == (0.0, 1.0)


def test_bootstrap_is_stratified_by_task() -> None:
    # Task 0 always scores 0, task 1 always 10: every stratified resample keeps 3 of each.
    scores = np.array([[0.0, 10.0]] * 3)
    assert stratified_bootstrap_ci(scores, "mean") == (5.0, 5.0)


@pytest.mark.parametrize("stat", ["mean", "iqm"])
def test_bootstrap_covers_the_true_centre(stat: str) -> None:
    """400 independent samples of 20 from N(0, 1) (one per 'point'); the true mean and IQM
    are 0. The percentile bootstrap covers slightly under 95% at n=20 (≈ 93%); with 400
    samples the binomial standard error is ≈ 1.3 points, so 89–98% is > 3 of them."""
    scores = np.random.default_rng(7).normal(size=(20, 1, 400))
    low, high = stratified_bootstrap_ci(scores, stat, seed=3)
    coverage = float(np.mean((low <= 0) & (high >= 0)))
    assert 0.89 <= coverage <= 0.98, coverage
    centre = aggregate(scores[:, 0, :], stat, axis=0)
    assert ((low <= centre) & (centre <= high)).all()


def test_help_shows_95_percent() -> None:
    result = subprocess.run(
        [str(BIN / "fedhpg-plot"), "--help"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0
    assert "95%" in result.stdout and "%%" not in result.stdout


def test_out_into_a_missing_directory_is_one_line_and_creates_nothing(
    sweep: Path, tmp_path: Path
) -> None:
    out = tmp_path / "missing" / "deeper" / "x.png"
    result = subprocess.run(
        [str(BIN / "fedhpg-plot"), str(sweep), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert result.stderr == f"fedhpg-plot: error: --out: {out.parent}: no such directory\n"
    assert not (tmp_path / "missing").exists()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["{tmp}/nope"], "{tmp}/nope: no such file or directory"),
        (["{tmp}/empty"], "{tmp}/empty: no run here (no metrics.jsonl in it or below)"),
        (["{tmp}/empty/notes.txt"], "{tmp}/empty/notes.txt: not a run directory or a metrics"),
        (["{sweep}", "--metric", "loss"], "argument --metric: invalid choice: 'loss'"),
        (["{sweep}", "--label", "a", "--label", "b", "--label", "c"], "--label: 3 label(s)"),
        (["{sweep}", "--out", "{tmp}/x.pdf"], "--out: {tmp}/x.pdf: must end in .png"),
        (["{sweep}", "--out", "{tmp}"], "--out: {tmp} is a directory"),
        (["{one}", "--per-agent", "--metric", "eval_worst_return"], "--per-agent: eval_worst"),
        (["{torn}"], "{torn}/metrics.jsonl line 2: not a JSON record"),
        (["{noeval}"], "nothing to plot for eval_return: the runs have no evaluation rounds"),
        (
            ["{cartpole}", "--metric", "eval_success", "--out", "{tmp}/c.png"],
            "--metric: eval_success: {cartpole} runs env.family=cartpole, whose episodes have "
            "no goal: it records no success rate (plot eval_return or eval_worst_return)",
        ),
        (
            ["{cartpole}", "--metric", "eval_success", "--per-agent", "--out", "{tmp}/c.png"],
            "--metric: eval_success:",
        ),
    ],
)
def test_bad_input_is_one_line_exit_2(
    arguments: list[str],
    message: str,
    sweep: Path,
    single_point: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("not a run")
    torn = tmp_path / "torn"
    torn.mkdir()
    (torn / "config.json").write_text((single_point / "config.json").read_text())
    first = (single_point / "metrics.jsonl").read_text().splitlines()[0]
    (torn / "metrics.jsonl").write_text(first + "\n" + first[:20] + "\n")
    noeval = tmp_path / "noeval"
    noeval.mkdir()
    (noeval / "config.json").write_text((single_point / "config.json").read_text())
    record = json.loads(first)
    del record["eval"]
    (noeval / "metrics.jsonl").write_text(json.dumps(record) + "\n")
    cartpole = tmp_path / "cartpole"  # what a CartPole run writes: success_rate 0 throughout
    cartpole.mkdir()
    (cartpole / "config.json").write_text(json.dumps(to_dict(compose(["env=cartpole"]))))
    record = json.loads(first)
    for evaluation in record["eval"].values():
        evaluation["success_rate"] = 0.0
    (cartpole / "metrics.jsonl").write_text(json.dumps(record) + "\n")
    names = {
        "tmp": tmp_path,
        "sweep": sweep,
        "one": single_point,
        "torn": torn,
        "noeval": noeval,
        "cartpole": cartpole,
    }
    before = sorted(tmp_path.rglob("*"))
    try:
        code = main([a.format(**names) for a in arguments])
    except SystemExit as exit_:  # argparse's own checks
        code = exit_.code
    assert code == 2
    stderr = capsys.readouterr().err
    assert stderr.count("\n") == 1 and stderr.startswith("fedhpg-plot: error: ")
    assert message.format(**names) in stderr
    assert sorted(tmp_path.rglob("*")) == before, "nothing written"


def test_plot_writes_png_and_svg(sweep: Path, tmp_path: Path) -> None:
    out = tmp_path / "curves.png"
    assert main([str(sweep), "--x", "trajectories", "--stat", "median", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000 and out.with_suffix(".svg").stat().st_size > 1000


def _overlap(a: object, b: object) -> bool:
    return bool(a.overlaps(b))  # type: ignore[attr-defined]


def test_round_ticks_are_whole_rounds_and_the_legend_leaves_the_data_alone(sweep: Path) -> None:
    groups = group_runs(find_runs([sweep]))
    figure = draw(groups, x_axis="rounds", metric="eval_return")
    axis = figure.axes[0]
    figure.canvas.draw()
    ticks = [t for t in axis.get_xticks() if axis.get_xlim()[0] <= t <= axis.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks), ticks
    renderer = figure.canvas.get_renderer()  # type: ignore[attr-defined]
    legend_box = axis.get_legend().get_window_extent(renderer)
    assert not _overlap(legend_box, axis.get_window_extent(renderer)), "legend over the data"
    plt.close(figure)


def test_the_title_says_what_ran_unless_given(sweep: Path) -> None:
    groups = group_runs(find_runs([sweep]))
    figure = draw(groups, x_axis="rounds", metric="eval_return")
    title = figure.axes[0].get_title()
    assert "gridworld" in title and "K=4" in title and title != "fedhpg learning curves"
    plt.close(figure)
    figure = draw(groups, x_axis="rounds", metric="eval_return", title="mine")
    assert figure.axes[0].get_title() == "mine"
    plt.close(figure)


def test_one_seed_is_not_called_a_mean_over_seeds(single_point: Path) -> None:
    figure = draw(group_runs(find_runs([single_point])), x_axis="rounds", metric="eval_return")
    title = figure.axes[0].get_legend().get_title().get_text()
    assert "over seeds" not in title and "one seed" in title, title
    plt.close(figure)
