"""``fedhpg-plot``: learning curves from any set of run directories, with a 95% band.

Runs are found by their ``metrics.jsonl`` (a sweep directory works as a whole) and grouped by
the compared config keys that differ between them (``common/configuration/run_roles.py`` GROUPS,
seeds aside); each group is one curve: the mean (``--stat median`` or ``iqm``) over its seeds and a
95% percentile-bootstrap confidence band around it (:mod:`fedhpg.server.commands.plot_stats` says
why not a t-interval). The drawing helpers (:func:`draw_band`, :func:`save`) are also what the
benchmarks' figures use, so every figure of the project follows one convention.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import numpy as np

from fedhpg.common.configuration.config import from_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import import_plugins
from fedhpg.common.configuration.run_roles import (
    DIAGNOSTIC_KEYS,
    GROUPS,
    PLACEMENT_KEYS,
    REPLICATE_KEYS,
)
from fedhpg.common.runtime.cli import version_text
from fedhpg.server.commands.plot_stats import STATS, Band, band_over_seeds, caption

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

logger = logging.getLogger(__name__)

X_AXES = {
    "rounds": "round",
    "trajectories": "trajectories per agent",
    "emulated": "emulated device time (s)",
}
# (y label of the curve over all agents, y label of one agent's curve with --per-agent)
METRICS = {
    "eval_return": (
        "greedy return, mean over the agents' environments",
        "greedy return in the agent's own environment",
    ),
    "eval_success": (
        "success rate, mean over the agents' environments",
        "success rate in the agent's own environment",
    ),
    "eval_worst_return": ("greedy return in the worst agent's environment", ""),
    "train_return": (
        "training return, mean over agents",
        "training return of the agent's own batch",
    ),
}
MARKER_POINTS = 30
"""Curves with at most this many points get a marker at each: an evaluation every few
rounds is then visible as such, and a single evaluation is a dot instead of nothing."""

# How the keys that tell groups apart read in a legend: the paper's symbols where it has one.
SYMBOLS = {
    "agents.budget.batch_size": "B",
    "agents.budget.local_iters": "τ",
    "agents.budget.inner_steps": "N",
    "agents.budget.mini_batch_size": "b",
    "agents.num_agents": "K",
    "algo.step_size": "η",
    "env.gamma": "γ",
}
VALUE_ONLY = {"algo.name", "strategy.name", "env.family"}  # the value names itself
NAMES = {"fedhpg": "FedHPG", "fedhpgvr": "FedHPGVR"}


class PlotError(ValueError):
    pass


@dataclass(frozen=True)
class Run:
    path: Path
    config: dict[str, Any]
    records: list[dict[str, Any]]


def _flatten(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, dict) and value:
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _natural(path: Path) -> list[Any]:
    """Sort key that puts sweep job 2 before job 10 (Hydra numbers jobs in sweep order)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", str(path))]


def _read_run(metrics: Path) -> Run | None:
    config_path = metrics.parent / "config.json"
    if not config_path.is_file():
        raise PlotError(f"{metrics.parent}: has metrics.jsonl but no config.json")
    try:
        config = json.loads(config_path.read_text(encoding="utf-8"))
        lines = metrics.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise PlotError(f"{metrics.parent}: cannot read its run files: {error}") from None
    if not isinstance(config, dict):
        raise PlotError(f"{config_path}: not a fedhpg run config")
    records = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            raise PlotError(f"{metrics} line {number}: not a JSON record") from None
        if not isinstance(record, dict) or "round" not in record or "agents" not in record:
            raise PlotError(f"{metrics} line {number}: not a fedhpg round record")
        records.append(record)
    if not records:
        logger.warning("%s: no rounds recorded yet, left out", metrics.parent)
        return None
    return Run(metrics.parent, config, records)


def find_runs(paths: list[Path]) -> list[Run]:
    """Every run under ``paths`` (run directories, sweep directories or metrics.jsonl files);
    PlotError for a path that does not exist or holds no run."""
    runs = []
    for root in paths:
        if not root.exists():
            raise PlotError(f"{root}: no such file or directory")
        if root.is_dir():
            found = sorted(root.rglob("metrics.jsonl"), key=_natural)
            if not found:
                raise PlotError(f"{root}: no run here (no metrics.jsonl in it or below)")
        elif root.name == "metrics.jsonl":
            found = [root]
        else:
            raise PlotError(f"{root}: not a run directory or a metrics.jsonl file")
        runs += [run for metrics in found if (run := _read_run(metrics)) is not None]
    if not runs:
        raise PlotError(f"no rounds recorded under {', '.join(map(str, paths))}")
    return runs


def _compared(key: str) -> bool:
    """Whether runs that differ in ``key`` are different experiments (config.GROUPS); seeds
    are replicates, and operational keys (server, security, ...) never matter."""
    if key in REPLICATE_KEYS or key in PLACEMENT_KEYS or key in DIAGNOSTIC_KEYS:
        return False
    role = GROUPS.get(key.split(".", 1)[0])
    return role is None or role.compared


def _value(value: Any) -> str:
    if isinstance(value, list):
        if value and all(v == value[0] for v in value):
            return _value(value[0])  # one value per agent, all the same: say it once
        return "(" + ", ".join(_value(v) for v in value) + ")"
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return NAMES.get(value, value)
    return json.dumps(value, separators=(",", ":"))


def _names(keys: list[str]) -> dict[str, str]:
    """Each key's name in a legend: its symbol, else its shortest dotted suffix that no other
    varying key ends with (``step_size`` alone would not tell algo from strategy)."""
    names = {}
    for key in keys:
        if key in SYMBOLS:
            names[key] = SYMBOLS[key]
            continue
        parts = key.split(".")
        for size in range(1, len(parts) + 1):
            suffix = ".".join(parts[-size:])
            if not any(other != key and other.endswith("." + suffix) for other in keys):
                names[key] = suffix
                break
    return names


def describe(key: str, value: Any, name: str) -> str:
    """``algo.name=fedhpgvr`` → "FedHPGVR"; ``agents.budget.batch_size=[2,5]`` → "B=(2, 5)"."""
    if key in VALUE_ONLY:
        return _value(value)
    if key == "attack.kind":
        return "no attack" if value == "none" else f"attack: {value}"
    return f"{name}={_value(value)}"


def group_runs(runs: list[Run]) -> dict[str, list[Run]]:
    """Label each run by the compared config keys whose values differ across the runs that
    have them (a key only one algorithm has, set alike wherever it is, is part of what the
    algorithm's name says); groups in the order their first run was found."""
    flats = [_flatten(run.config) for run in runs]
    keys = sorted({k for flat in flats for k in flat}, key=lambda k: (k not in VALUE_ONLY, k))
    varying = [
        k for k in keys if _compared(k) and len({json.dumps(f[k]) for f in flats if k in f}) > 1
    ]
    names = _names(varying)
    groups: dict[str, list[Run]] = {}
    for run, flat in zip(runs, flats, strict=True):
        parts = [describe(k, flat[k], names[k]) for k in varying if k in flat]
        groups.setdefault(", ".join(parts) or "all runs", []).append(run)
    return groups


def relabel(groups: dict[str, list[Run]], labels: list[str]) -> dict[str, list[Run]]:
    """``--label``: either GROUP=LABEL for some groups (GROUP as the legend shows it without
    --label), or one label per group in the legend's order."""
    if not labels:
        return groups
    mapping: dict[str, str] = {}
    for text in labels:
        matches = [g for g in groups if text.startswith(g + "=")]
        if not matches:
            break
        group = max(matches, key=len)
        mapping[group] = text[len(group) + 1 :]
    else:
        return {mapping.get(g, g): runs for g, runs in groups.items()}
    if len(labels) != len(groups):
        raise PlotError(
            f"--label: {len(labels)} label(s) for {len(groups)} group(s) "
            f"({'; '.join(groups)}): give one per group in that order, or GROUP=LABEL"
        )
    return dict(zip(labels, groups.values(), strict=True))


def series(
    run: Run, x_axis: str, metric: str, agent: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of one run; with ``agent``, the metric in that agent's environment only."""
    xs, ys = [], []
    trajectories = emulated = 0.0
    for record in run.records:
        agents = record["agents"]
        # Files written before the counter existed: sum it here the same way.
        trajectories = record.get(
            "trajectories_per_agent",
            trajectories + sum(a["trajectories"] for a in agents) / max(len(agents), 1),
        )
        if "emulated_clock_s" in record:  # buffered rounds: the clock at the aggregation
            emulated = float(record["emulated_clock_s"])
        else:  # a round in which no update arrived (deadline policy) took no device time here
            emulated += max((a.get("emulated_s", 0.0) for a in agents), default=0.0)
        x = {"rounds": record["round"], "trajectories": trajectories, "emulated": emulated}[x_axis]
        if metric == "train_return":
            chosen = [a for a in agents if agent is None or a["id"] == agent]
            if not chosen:
                continue  # that agent's update was not averaged this round
            y = float(np.mean([a["train_return"] for a in chosen]))
        elif "eval" not in record:
            continue
        elif agent is not None:
            key = "success_rate" if metric == "eval_success" else "return_mean"
            y = float(record["eval"][agent][key])
        elif metric == "eval_return":
            y = float(np.mean([e["return_mean"] for e in record["eval"].values()]))
        elif metric == "eval_worst_return":
            y = float(min(e["return_mean"] for e in record["eval"].values()))
        else:
            y = float(np.mean([e["success_rate"] for e in record["eval"].values()]))
        xs.append(x)
        ys.append(y)
    return np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)


def _seeds(count: int) -> str:
    return f"{count} seed" + ("" if count == 1 else "s") + (", no band" if count == 1 else "")


def draw_band(
    axis: Axes,
    label: str,
    curves: list[tuple[np.ndarray, np.ndarray]],
    *,
    stat: str = "mean",
    band_alpha: float = 0.2,
    **style: Any,
) -> tuple[Line2D, Band]:
    """One group's curve: ``stat`` over its seeds' (x, y) curves and the bootstrap band, a
    marker at every point when there are few, the seed count in the legend entry."""
    band = band_over_seeds(curves, stat)
    if band.x.size <= MARKER_POINTS:
        style.setdefault("marker", "o")
        style.setdefault("markersize", 4)
    (line,) = axis.plot(band.x, band.centre, label=f"{label} ({_seeds(band.seeds)})", **style)
    if band.seeds > 1:
        axis.fill_between(
            band.x, band.low, band.high, color=line.get_color(), alpha=0.2, linewidth=0
        )
    return line, band


def legend(axis: Axes, stat: str, *, seeds: int = 2, **options: Any) -> None:
    """The legend, titled with what the curves and bands are (``seeds``: the most any curve
    has). Without a ``loc`` it sits to the right of the axes, never over the data."""
    if "loc" not in options:
        options.update(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    options.setdefault("fontsize", "small")
    axis.legend(title=caption(stat, seeds=seeds), title_fontsize="small", **options)


def save(figure: Figure, out: Path) -> None:
    """``out`` (PNG) and the same figure as SVG beside it."""
    import matplotlib.pyplot as plt

    figure.tight_layout()
    try:  # "tight": a legend beside the axes is inside the image
        figure.savefig(out, dpi=120, bbox_inches="tight")
        # No date in the SVG: a redrawn figure whose data did not change stays the same file.
        figure.savefig(out.with_suffix(".svg"), metadata={"Date": None}, bbox_inches="tight")
    except OSError as error:
        raise PlotError(f"--out: cannot write {out}: {error.strerror or error}") from None
    finally:
        plt.close(figure)


def figure_and_axis() -> tuple[Figure, Axes]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(7, 4.2))


def check_out(out: Path) -> None:
    """Refuse an --out that cannot be written, before anything is drawn: nothing is created
    outside what was asked for (a missing directory is the user's to make)."""
    if out.is_dir():
        raise PlotError(f"--out: {out} is a directory; name the .png file")
    if out.suffix.lower() != ".png":
        raise PlotError(f"--out: {out}: must end in .png (the .svg is written beside it)")
    parent = out.parent
    if not parent.is_dir():
        what = "is not a directory" if parent.exists() else "no such directory"
        raise PlotError(f"--out: {parent}: {what}")


def agent_setting(run: Run, index: int) -> str:
    """What is particular to agent ``index`` in ``run``: the per-agent lists of the config
    (``agents.budget.batch_size=[2,5,10,20]`` → "B=5" for agent 1) whose entries differ."""
    flat = _flatten(run.config)
    count = run.config.get("agents", {}).get("num_agents")
    keys = [
        k
        for k, v in flat.items()
        if k.startswith("agents.") and isinstance(v, list) and len(v) == count > 1
        and len({json.dumps(e) for e in v}) > 1
    ]  # fmt: skip
    names = _names(keys)
    return ", ".join(f"{names[k]}={_value(flat[k][index])}" for k in keys)


def records_success(run: Run) -> bool:
    """Whether the episodes of ``run``'s environment can reach a goal (``has_goal``): only
    then is its success rate a measurement (metrics.jsonl holds 0 where there is none, as a
    failed task would read). True where the family cannot be built here (a plugin that is not
    installed, a config of another version): its records are drawn as they are."""
    try:
        config = from_dict(run.config)
        import_plugins(list(config.plugins))
        from fedhpg.common.heterogeneity.variants import variant_of

        return bool(variant_of(config, 0).has_goal)
    except (ConfigError, ImportError, OSError, ValueError, TypeError, KeyError):
        return True


def curves_of(
    groups: dict[str, list[Run]], *, x_axis: str, metric: str, per_agent: bool
) -> list[tuple[str, list[tuple[np.ndarray, np.ndarray]]]]:
    """(legend label, the seeds' curves) of every curve to draw; PlotError when none has a
    point of ``metric``."""
    if per_agent and not METRICS[metric][1]:
        raise PlotError(f"--per-agent: {metric} is over all agents; use --metric eval_return")
    if metric == "eval_success":
        for run in (run for runs in groups.values() for run in runs):
            if not records_success(run):
                family = run.config.get("env", {}).get("family")
                raise PlotError(
                    f"--metric: eval_success: {run.path} runs env.family={family}, whose "
                    "episodes have no goal: it records no success rate (plot eval_return or "
                    "eval_worst_return)"
                )
    drawn = []
    for label, runs in groups.items():
        agents = runs[0].records[0]["agents"] if per_agent else [None]
        for agent in agents:
            agent_id = None if agent is None else agent["id"]
            try:
                curves = [series(run, x_axis, metric, agent_id) for run in runs]
            except KeyError as error:
                raise PlotError(f"{runs[0].path}: its records lack {error}") from None
            curves = [c for c in curves if len(c[0])]
            if not curves:
                continue
            name = label
            if agent is not None:  # the agent's id and its own settings; the group if several
                own = agent_setting(runs[0], agent["index"])
                name = f"{agent_id}: {own}" if own else str(agent_id)
                name = name if len(groups) == 1 else f"{label}, {name}"
            drawn.append((name, curves))
    if not drawn:
        hint = "no evaluation rounds (eval.every)" if metric.startswith("eval") else "no rounds"
        raise PlotError(f"nothing to plot for {metric}: the runs have {hint}")
    return drawn


def default_title(groups: dict[str, list[Run]]) -> str:
    """What every run drawn shares: the environment family, K, the algorithm and strategy
    (a value the runs differ in is left out: the legend says it)."""
    configs = [run.config for runs in groups.values() for run in runs]

    def shared(path: str) -> Any:
        values = set()
        for config in configs:
            node: Any = config
            for part in path.split("."):
                node = node.get(part) if isinstance(node, dict) else None
            values.add(json.dumps(node, sort_keys=True))
        return json.loads(values.pop()) if len(values) == 1 else None

    parts = []
    family = shared("env.family")
    if family is not None:
        identifier = shared("env.options.id") if family == "gym" else None
        parts.append(str(identifier or family))
    if (agents := shared("agents.num_agents")) is not None:
        parts.append(f"K={agents}")
    if (algorithm := shared("algo.name")) is not None:
        parts.append(NAMES.get(str(algorithm), str(algorithm)))
    if (strategy := shared("strategy.name")) is not None:
        parts.append(f"strategy {strategy}")
    return ", ".join(parts) or "fedhpg learning curves"


def draw(
    groups: dict[str, list[Run]],
    *,
    x_axis: str,
    metric: str,
    title: str | None = None,
    per_agent: bool = False,
    stat: str = "mean",
) -> Figure:
    """The figure of every group's curve (not saved: :func:`plot` does that). ``title``:
    by default what the runs share (:func:`default_title`)."""
    from matplotlib.ticker import MaxNLocator

    drawn = curves_of(groups, x_axis=x_axis, metric=metric, per_agent=per_agent)
    figure, axis = figure_and_axis()
    seeds = 0
    for label, curves in drawn:
        _, band = draw_band(axis, label, curves, stat=stat)
        seeds = max(seeds, band.seeds)
    if x_axis == "rounds":
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.set_xlabel(X_AXES[x_axis])
    axis.set_ylabel(METRICS[metric][1 if per_agent else 0])
    axis.set_title(default_title(groups) if title is None else title)
    legend(axis, stat, seeds=seeds)
    return figure


def plot(groups: dict[str, list[Run]], *, out: Path, **options: Any) -> int:
    """Draw every group into ``out`` (and its .svg); returns the number of curves."""
    check_out(out)
    figure = draw(groups, **options)
    count = len(figure.axes[0].get_lines())
    save(figure, out)
    return count


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        """One line, exit 2 (argparse's default prints the whole usage first)."""
        self.exit(2, f"{self.prog}: error: {message}\n")


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(
        prog="fedhpg-plot",
        description="Learning curves per group of runs (groups: the config keys that differ "
        "between runs, seeds aside): the mean (or median, IQM) over seeds and its 95% "
        "percentile-bootstrap confidence band.",
    )
    parser.add_argument("paths", nargs="+", type=Path, help="run or sweep directories")
    parser.add_argument("--x", choices=sorted(X_AXES), default="rounds", help="x axis")
    parser.add_argument("--metric", choices=sorted(METRICS), default="eval_return")
    parser.add_argument(
        "--stat",
        choices=STATS,
        default="mean",
        help="statistic over seeds (iqm: interquartile mean); the band is its 95%% CI",
    )
    parser.add_argument(
        "--label",
        action="append",
        default=[],
        metavar="LABEL",
        help="legend label: once per group in the legend's order, or GROUP=LABEL",
    )
    parser.add_argument(
        "--out", type=Path, default=Path("curves.png"), help="PNG (an .svg is written beside)"
    )
    parser.add_argument(
        "--title", help="the figure's title (default: what the runs share: env, K, algorithm)"
    )
    parser.add_argument(
        "-V", "--version", action="version", version=version_text(parser.prog).strip()
    )
    parser.add_argument(
        "--per-agent", action="store_true", help="one curve per agent (its own environment)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        check_out(args.out)
        groups = relabel(group_runs(find_runs(args.paths)), args.label)
        count = plot(
            groups,
            x_axis=args.x,
            metric=args.metric,
            out=args.out,
            title=args.title,
            per_agent=args.per_agent,
            stat=args.stat,
        )
    except PlotError as error:
        sys.stderr.write(f"fedhpg-plot: error: {error}\n")
        return 2
    logger.info("wrote %s and %s (%d curves)", args.out, args.out.with_suffix(".svg"), count)
    return 0


def entry() -> None:
    sys.exit(main())
