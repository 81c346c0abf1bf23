"""``fedhpg-plot``: learning curves from any set of run directories, mean and 95% band.

Runs are found by their ``metrics.jsonl`` (a sweep directory works as a whole) and grouped by
the config keys that differ between them, seeds excepted; each group is one curve: the mean
over its seeds and a 95% confidence band (Student t) around it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fedhpg.common.config import GROUPS, REPLICATE_KEYS

logger = logging.getLogger(__name__)

X_AXES = {
    "rounds": "round",
    "trajectories": "trajectories per agent",
    "emulated": "emulated time (s)",
}
METRICS = {
    "eval_return": "greedy return, mean over environments",
    "eval_success": "success rate, mean over environments",
    "eval_worst_return": "greedy return in the worst environment",
    "train_return": "training return, mean over agents",
}
# Two-sided 97.5% Student-t quantiles by degrees of freedom (1..30); normal beyond.
T_975 = [12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
         2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
         2.060, 2.056, 2.052, 2.048, 2.045, 2.042]  # fmt: skip


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


def find_runs(paths: list[Path]) -> list[Run]:
    runs = []
    for root in paths:
        if not root.exists():
            raise PlotError(f"{root}: no such file or directory")
        for metrics in sorted(root.rglob("metrics.jsonl")) if root.is_dir() else [root]:
            config_path = metrics.parent / "config.json"
            if not config_path.exists():
                raise PlotError(f"{metrics.parent}: has metrics.jsonl but no config.json")
            lines = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
            if lines:
                runs.append(Run(metrics.parent, json.loads(config_path.read_text()), lines))
    if not runs:
        raise PlotError(f"no metrics.jsonl found under {', '.join(map(str, paths))}")
    return runs


def _compared(key: str) -> bool:
    """Whether runs that differ in ``key`` are different experiments (config.GROUPS); seeds
    are replicates, and operational keys (server, security, ...) never matter."""
    if key in REPLICATE_KEYS:
        return False
    role = GROUPS.get(key.split(".", 1)[0])
    return role is None or role.compared


def group_runs(runs: list[Run]) -> dict[str, list[Run]]:
    """Label each run by the compared config keys whose values differ across runs."""
    flats = [_flatten(run.config) for run in runs]
    keys = sorted({k for flat in flats for k in flat})
    varying = [k for k in keys if _compared(k) and len({json.dumps(f.get(k)) for f in flats}) > 1]
    groups: dict[str, list[Run]] = {}
    for run, flat in zip(runs, flats, strict=True):
        label = (
            ", ".join(f"{k.split('.')[-1]}={_short(flat.get(k))}" for k in varying) or "all runs"
        )
        groups.setdefault(label, []).append(run)
    return groups


def _short(value: Any) -> str:
    if isinstance(value, list) and len(set(map(str, value))) == 1:
        return str(value[0])
    return json.dumps(value).replace(" ", "")


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
            trajectories + sum(a["trajectories"] for a in agents) / len(agents),
        )
        emulated += max(a.get("emulated_s", 0.0) for a in agents)
        x = {"rounds": record["round"], "trajectories": trajectories, "emulated": emulated}[x_axis]
        if metric == "train_return":
            chosen = [a for a in agents if agent is None or a["id"] == agent]
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


def mean_and_band(curves: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, ...]:
    """Mean and 95% confidence band over seeds on the first curve's x grid."""
    grid = curves[0][0]
    values = np.stack([np.interp(grid, x, y) for x, y in curves])
    mean = values.mean(axis=0)
    n = values.shape[0]
    if n < 2:
        return grid, mean, mean, mean
    t = T_975[n - 2] if n - 1 <= len(T_975) else 1.96
    half = t * values.std(axis=0, ddof=1) / math.sqrt(n)
    return grid, mean, mean - half, mean + half


def plot(
    groups: dict[str, list[Run]],
    *,
    x_axis: str,
    metric: str,
    out: Path,
    title: str,
    per_agent: bool = False,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4.2))
    for label, runs in groups.items():
        agents = [a["id"] for a in runs[0].records[0]["agents"]] if per_agent else [None]
        for agent in agents:
            curves = [series(run, x_axis, metric, agent) for run in runs]
            curves = [c for c in curves if len(c[0])]
            if not curves:
                continue
            grid, mean, low, high = mean_and_band(curves)
            name = label if agent is None else f"{label}, {agent}"
            (line,) = axis.plot(grid, mean, label=f"{name} (n={len(curves)})")
            axis.fill_between(grid, low, high, color=line.get_color(), alpha=0.2)
    axis.set_xlabel(X_AXES[x_axis])
    axis.set_ylabel(METRICS[metric])
    axis.set_title(title)
    axis.legend(loc="best", fontsize="small")
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=120)
    figure.savefig(out.with_suffix(".svg"))
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="fedhpg-plot",
        description="Mean and 95%% confidence band per group of runs (groups: the config "
        "keys that differ between runs, seeds aside).",
    )
    parser.add_argument("paths", nargs="+", type=Path, help="run or sweep directories")
    parser.add_argument("--x", choices=sorted(X_AXES), default="rounds", help="x axis")
    parser.add_argument("--metric", choices=sorted(METRICS), default="eval_return")
    parser.add_argument("--out", type=Path, default=Path("curves.png"), help="PNG (and .svg)")
    parser.add_argument("--title", default="fedhpg learning curves")
    parser.add_argument(
        "--per-agent", action="store_true", help="one curve per agent (its own environment)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        groups = group_runs(find_runs(args.paths))
        plot(
            groups,
            x_axis=args.x,
            metric=args.metric,
            out=args.out,
            title=args.title,
            per_agent=args.per_agent,
        )
    except (PlotError, json.JSONDecodeError, KeyError) as error:
        sys.stderr.write(f"error: {error}\n")
        return 2
    logger.info("wrote %s and %s (%d curves)", args.out, args.out.with_suffix(".svg"), len(groups))
    return 0


def entry() -> None:
    sys.exit(main())
