"""The result tables of the device benchmark (``benchmarks/on_device.sh``: its report,
``bench_device.json``, from :mod:`benchmarks.scale_device`, and the profile,
``device_profile.json``, from :mod:`benchmarks.device_profile`).

    python -m benchmarks.device_tables device_h200 OUT/bench_device.json
    python -m benchmarks.device_tables device_cpu_rehearsal \\
        benchmarks/results/bench_device_cpu.json benchmarks/results/device_profile_cpu.json
    python -m benchmarks.device_tables --tables-only

With a result's name and the run's files it writes ``benchmarks/results/tables/<name>.json``
(``device_cpu_rehearsal`` writes ``device_cpu_ratio`` too), stamped today at this commit with
the machine the report names. ``--tables-only`` writes every device table again from the data
files each stored result names, keeping the date, commit and machine of that measurement.
No torch here: the tables are read from the JSON alone.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from benchmarks import results_file

NAMES = ("device_h200", "device_cpu_rehearsal", "device_cpu_ratio")
FAMILIES = {
    "cartpole": "CartPole",
    "acrobot": "Acrobot",
    "mountaincar": "MountainCar",
    "gridworld": "GridWorld",
    "pendulum": "Pendulum",
}
PLACEMENT_KEYS = ("same_theta_in_any_company", "same_theta_on_a_second_run")


def _iterations(record: dict[str, Any]) -> list[tuple[dict[str, Any], dict[str, Any] | None]]:
    """Every engine row of the report's iteration parts with its K's reference, in K order."""
    rows, refs = [], {}
    for part in record["parts"].values():
        if part["part"] == "iteration":
            rows += part["rows"]
            refs.update({r["agents"]: r for r in part["reference"]})
    rows.sort(key=lambda r: r["agents"])
    return [(r, refs.get(r["agents"])) for r in rows]


def _ratio(row: dict[str, Any], ref: dict[str, Any] | None) -> float | None:
    return None if ref is None else row["steps_per_s"] / ref["with_gradient_steps_per_s"]


def _millions(steps_per_s: float) -> str:
    value = steps_per_s / 1e6
    return f"{value:,.1f}" if value >= 1 else f"{value:.3g}"


def _cell(value: Any, scale: float = 1.0, digits: int = 2) -> str:
    """``value`` (a number, or None or no reference: a dash) scaled and rounded."""
    return "—" if value is None else f"{value / scale:,.{digits}f}"


def iteration_table(record: dict[str, Any]) -> str:
    """One local iteration of every agent at each K and policy against the reference; the
    reference's peak memory where it was measured (on a GPU)."""
    found = _iterations(record)
    ref_peak = any(ref is not None and ref.get("peak_mib") is not None for _, ref in found)
    lines = [
        "| K | policy | env steps / iteration | iteration (s) | engine (M steps/s) "
        "| reference sampling (M/s) | reference + gradient (M/s) "
        "| engine ÷ reference + gradient | device peak (MiB) | planned peak (MiB) |"
        + (" reference peak (MiB) |" if ref_peak else ""),
        "|---|---|---|---|---|---|---|---|---|---|" + ("---|" if ref_peak else ""),
    ]
    for row, ref in found:
        policy = row["policy"] + ("" if row.get("measured_rounds", 1) else " (1 round)")
        lines.append(
            f"| {row['agents']:,} | {policy} | {row['env_steps']:,} | {row['iteration_s']:.3f} "
            f"| {_millions(row['steps_per_s'])} "
            f"| {_cell(ref and ref['sampling_steps_per_s'], 1e6, 1)} "
            f"| {_cell(ref and ref['with_gradient_steps_per_s'], 1e6, 1)} "
            f"| {_cell(_ratio(row, ref))} | {_cell(row['device_peak_mib'], digits=0)} "
            f"| {row['planned_peak_mib']:,.0f} |"
            + (f" {_cell(ref and ref.get('peak_mib'), digits=0)} |" if ref_peak else "")
        )
    return "\n".join(lines)


def _where(record: dict[str, Any]) -> str:
    return (
        "On one CPU thread" if record.get("device") == "cpu" else f"On the {record['device_name']}"
    )


def iteration_summary(record: dict[str, Any]) -> str:
    """The engine's ratio to the reference with its gradient: its range, and at the largest K
    measured; whether the device's peak stayed inside the planned one."""
    found = [(row, ratio) for row, ref in _iterations(record) if (ratio := _ratio(row, ref))]
    if not found:
        return "No engine row measured against the reference."
    ratios = [ratio for _, ratio in found]
    low = min(found, key=lambda f: f[1])[0]["policy"]
    high = max(found, key=lambda f: f[1])[0]["policy"]
    largest = max(row["agents"] for row, _ in found)
    best_row, best = max(
        ((row, ratio) for row, ratio in found if row["agents"] == largest), key=lambda f: f[1]
    )
    over = [
        f"{row['agents']:,} ({row['policy']})"
        for row, _ in _iterations(record)
        if row["device_peak_mib"] is not None and row["device_peak_mib"] > row["planned_peak_mib"]
    ]
    memory = (
        "the device's peak memory stayed inside the plan at every K"
        if not over
        else f"the device's peak memory exceeded the plan at K = {', '.join(over)}"
    )
    return (
        f"{_where(record)} the engine does {min(ratios):.2f}–{max(ratios):.2f} × the reference "
        f"with its gradient, least with the {low} policy, most with the {high} one; at "
        f"K = {largest:,} {_millions(best_row['steps_per_s'])} M env steps/s, {best:.2f} × the "
        f"reference's; {memory}."
    )


def ratio_table(record: dict[str, Any]) -> str:
    lines = ["| K | policy | engine ÷ reference + gradient |", "|---|---|---|"]
    for row, ref in _iterations(record):
        lines.append(f"| {row['agents']:,} | {row['policy']} | {_cell(_ratio(row, ref))} |")
    return "\n".join(lines)


def ratio_summary(record: dict[str, Any]) -> str:
    ratios = [r for row, ref in _iterations(record) if (r := _ratio(row, ref)) is not None]
    if not ratios:
        return "No engine row measured against the reference."
    return f"{_where(record)} the engine does {min(ratios):.2f}–{max(ratios):.2f} × the reference."


SECTIONS = ("sampling", "estimator", "tiles", "tile gradients", "row sums", "the rest")


def profile_title(profile: dict[str, Any]) -> str:
    agents = sorted({entry["agents"] for entry in profile["rounds"]})
    return (
        "Where one iteration's time goes (ns per env step, "
        f"K = {', '.join(f'{k:,}' for k in agents)})"
    )


def profile_table(profile: dict[str, Any]) -> str:
    """Each section's ns per env step, the first's share of the sectioned iteration beside it."""
    lines = [f"| policy | {' | '.join(SECTIONS)} | iteration (s) |", "|---" * 8 + "|"]
    for entry in profile["rounds"]:
        steps, sections = entry["env_steps"], entry["sections_s"]
        cells = [f"{1e9 * sections[name] / steps:,.0f}" for name in SECTIONS]
        cells[0] += f" ({sections[SECTIONS[0]] / entry['sectioned_iteration_s']:.0%})".replace(
            "%", " %"
        )
        lines.append(
            f"| {entry['policy']} ({steps:,} steps) | {' | '.join(cells)} "
            f"| {entry['iteration_s']:.3f} |"
        )
    return "\n".join(lines)


def profile_summary(profile: dict[str, Any]) -> str:
    """Each policy's two heaviest sections and their shares of the sectioned iteration."""
    parts = []
    for entry in profile["rounds"]:
        sections = entry["sections_s"]
        heavy = sorted(SECTIONS, key=lambda name: sections[name], reverse=True)[:2]
        shares = [
            f"{name} {sections[name] / entry['sectioned_iteration_s']:.0%}".replace("%", " %")
            for name in heavy
        ]
        parts.append(f"{entry['policy']}: {' and '.join(shares)}")
    return "The heaviest sections of an iteration, by share: " + "; ".join(parts) + "."


def placement_table(record: dict[str, Any]) -> str:
    """Each family's two checks; the families that hold both first."""
    families = record["placement"]["families"]
    order = sorted(
        families,
        key=lambda f: (not all(families[f][k] for k in PLACEMENT_KEYS), list(FAMILIES).index(f)),
    )
    lines = [
        "| family | the same θ in any company | the same θ on a second run |",
        "|---|---|---|",
    ]
    for family in order:
        cells = ["yes" if families[family][key] else "no" for key in PLACEMENT_KEYS]
        lines.append(f"| {FAMILIES.get(family, family)} | {' | '.join(cells)} |")
    return "\n".join(lines)


def placement_summary(record: dict[str, Any]) -> str:
    families = record["placement"]["families"]

    def names(key: str, value: bool) -> list[str]:
        return [FAMILIES.get(f, f) for f in families if families[f][key] is value]

    held = [FAMILIES.get(f, f) for f in families if all(families[f][k] for k in PLACEMENT_KEYS)]
    text = f"θ is bit-identical in any company and on a second run for {', '.join(held) or 'none'}"
    company, second = names(PLACEMENT_KEYS[0], False), names(PLACEMENT_KEYS[1], False)
    if company:
        text += f"; it depends on the company for {', '.join(company)}"
    if second:
        text += f" and differs on a second run for {', '.join(second)}"
    return text + ' (docs/gpu.md, "Determinism on a GPU", says what the engine does about it).'


def federation_title(record: dict[str, Any]) -> str:
    federation = record["federation"]
    return (
        f"A whole federation: `fedhpg-run` with {federation['agents']:,} CartPole agents on one "
        f"agent host, `algo.engine=torch algo.device={record['device']}`"
    )


def federation_table(record: dict[str, Any]) -> str:
    federation = record["federation"]
    rounds = federation["rounds"]
    evaluated = [r for r in rounds if "eval_mean_return" in r]
    environments = evaluated[-1]["eval_environments"] if evaluated else federation["agents"]
    greedy = f"{evaluated[-1]['eval_mean_return']:.0f}" if evaluated else "—"
    times = ", ".join(f"{r['round_time_s']:.1f}" for r in rounds)
    return "\n".join(
        [
            "| rounds | from the command's start (s) | round times (s) "
            f"| greedy return of θ̃, mean over {environments:,} environments |",
            "|---|---|---|---|",
            f"| {len(rounds)} | {federation['seconds']:.0f} | {times} | {greedy} |",
        ]
    )


def federation_summary(record: dict[str, Any]) -> str:
    federation = record["federation"]
    done = federation["exit_status"] == 0
    where = f"one {record['device_name']}" if record.get("device") != "cpu" else "the CPU"
    verb = "runs" if done else f"exits with status {federation['exit_status']}"
    return (
        f"A federation of {federation['agents']:,} agents {verb} on {where} from `fedhpg-run`, "
        f"{len(federation['rounds'])} rounds in "
        f"{math.fsum(r['round_time_s'] for r in federation['rounds']):.1f} s."
    )


def tables(
    name: str, record: dict[str, Any], profile: dict[str, Any] | None = None
) -> list[results_file.Table]:
    """The tables of the result ``name`` from the report (and, for the rehearsal, the
    profile)."""
    md = results_file.table_from_markdown
    if name == "device_cpu_ratio":
        return [md(ratio_table(record), ratio_summary(record))]
    found = [md(iteration_table(record), iteration_summary(record))]
    if name == "device_cpu_rehearsal" and profile is not None:
        found.append(
            md(profile_table(profile), profile_summary(profile), title=profile_title(profile))
        )
    if name in ("device_h200", "device_cpu_rehearsal"):
        if record.get("placement"):
            found.append(
                md(
                    placement_table(record),
                    placement_summary(record),
                    title=f"Placement on {record['device'].upper()}: an agent's θ after round 3 "
                    "alone, in four companies, and on a second run (9 agents of the population)",
                )
            )
        if record.get("federation"):
            found.append(
                md(
                    federation_table(record),
                    federation_summary(record),
                    title=federation_title(record),
                )
            )
    return found


def stored_tables(name: str) -> list[results_file.Table]:
    """``name``'s tables from the data files its stored result names."""
    data = [results_file.ROOT / p for p in results_file.load(results_file.TABLES / f"{name}.json")
            .get("data", [])]  # fmt: skip
    if name == "device_cpu_ratio":  # the rehearsal's report
        data = [results_file.ROOT / p for p in results_file.load(
            results_file.TABLES / "device_cpu_rehearsal.json").get("data", [])][:1]  # fmt: skip
    record = json.loads(data[0].read_text())
    profile = json.loads(data[1].read_text()) if len(data) > 1 else None
    return tables(name, record, profile)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("name", nargs="?", choices=NAMES[:2])
    parser.add_argument("files", nargs="*", type=Path, help="the report, then the profile")
    parser.add_argument("--tables-only", action="store_true", help="every stored device table")
    args = parser.parse_args()
    if args.tables_only:
        for name in NAMES:
            results_file.rerender(name, stored_tables(name))
        return
    if args.name is None or not args.files:
        parser.error("a result's name and the run's report, or --tables-only")
    record = json.loads(args.files[0].read_text())
    profile = json.loads(args.files[1].read_text()) if len(args.files) > 1 else None
    machine = f"{record['machine']}; {record['device_name']}, torch {record['torch']}"
    data = [str(p) for p in args.files]
    names = [args.name] + (["device_cpu_ratio"] if args.name == "device_cpu_rehearsal" else [])
    for name in names:
        stored = results_file.load(results_file.TABLES / f"{name}.json")
        results_file.write(
            name,
            title=stored["title"],
            order=stored["order"],
            command=stored["command"],
            measures=stored["measures"],
            tables=tables(name, record, profile),
            setup=stored.get("setup"),
            data=None if name == "device_cpu_ratio" else data,
            machine_name=machine,
        )


if __name__ == "__main__":
    main()
