"""The one shape of a benchmark's result: what ``python -m benchmarks.render`` turns into a
section of BENCHMARKS.md.

A result file is ``benchmarks/results/tables/<name>.json``, one per benchmark section::

    {
      "title": "Defaults at K = 1,000",          # the section's heading
      "order": 10,                               # where the section goes (ascending)
      "command": "python -m benchmarks.defaults",# what a user runs to measure it again
      "date": "2026-12-04",                      # when it was measured
      "commit": "f37e761",                       # the commit it was measured at
      "machine": "Intel Xeon, 2 cores",          # CPU model and cores; the GPU where one
      "measures": ["server", "agent"],           # the paths whose change makes it stale
      "setup": "What was run, in prose.",        # optional: how to read the tables
      "data": ["benchmarks/results/defaults.json"],  # optional: the raw data beside it
      "tables": [{
        "title": "optional heading of one table",
        "command": "optional: this table's own command",
        "columns": ["K", "seconds"],
        "rows": [["1,000", "16.5"]],
        "summary": "One or two sentences a user reads the table by.",
        "figure": {"path": "docs/figures/x.png", "caption": "...", "ref": "x"}  # optional
      }]
    }

Every table of a file was measured with the same date, commit and machine: results from two
machines are two files, so no table mixes them. A figure with a ``ref`` is drawn as a
reference-style image (``![caption][ref]``) whose reference the docs site's page defines again
relative to docs/; without one the figure's path is named.

The raw data a benchmark keeps (curves, per-seed runs, what its tests and figures read) stays
in ``benchmarks/results/<name>.json`` in the shape its readers expect; ``data`` names it.
A benchmark script calls :func:`write` with its tables; :func:`write` stamps the date, the
commit (``git rev-parse --short HEAD``) and the machine, unless they are given (a result
transcribed from an earlier run keeps the ones it was measured with). A script whose section
is described once in its result file (title, measured paths, set-up) calls :func:`refresh`
instead, which keeps that description and replaces the tables and the stamps. Either way a
table re-measured to the very same columns and rows keeps the summary stored with it (one
written for those numbers), not the script's generic one.
"""

from __future__ import annotations

import datetime
import json
import os
import shlex
import shutil
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NotRequired, TypedDict

ROOT = Path(__file__).resolve().parents[1]
TABLES = ROOT / "benchmarks" / "results" / "tables"
LEARNING_CODE = (
    "common/learning/algorithms",
    "common/learning/estimators.py",
    "common/learning/engine",
    "common/learning/batched",
    "common/learning/policies.py",
    "common/learning/optim.py",
    "envs",
)
"""What a learning benchmark measures: a change here may change its returns."""
RUNTIME_CODE = ("server", "agent", "common/runtime", "common/wire")
"""What a benchmark of real federations measures besides the learning: processes and wire."""


class Figure(TypedDict):
    path: str
    caption: str
    ref: NotRequired[str]


class Table(TypedDict):
    columns: list[str]
    rows: list[list[str]]
    summary: str
    title: NotRequired[str]
    command: NotRequired[str]
    figure: NotRequired[Figure]


class Result(TypedDict):
    title: str
    order: int
    command: str
    date: str
    commit: str
    machine: str
    measures: list[str]
    tables: list[Table]
    setup: NotRequired[str]
    data: NotRequired[list[str]]


class ResultError(ValueError):
    """A result file that does not have the shape above; the message is one line."""


_REQUIRED: dict[str, type] = {
    "title": str,
    "order": int,
    "command": str,
    "date": str,
    "commit": str,
    "machine": str,
    "measures": list,
    "tables": list,
}
_OPTIONAL: dict[str, type] = {"setup": str, "data": list}
_TABLE_REQUIRED: dict[str, type] = {"columns": list, "rows": list, "summary": str}
_TABLE_OPTIONAL: dict[str, type] = {"title": str, "command": str, "figure": dict}


def commit(root: Path = ROOT) -> str:
    """The short hash of the checked-out commit, ``unknown`` outside a git checkout (the
    renderer then refuses the result in one line)."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def cpu_description(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU the figures were measured on, e.g. ``AMD EPYC, 2 cores, AVX2``: ratios against
    a numpy or torch reference depend on it, since stacked matmuls and compiled kernels gain
    unequally from wider vectors (AVX-512 against AVX2)."""
    model, flags = "unknown CPU", set[str]()
    try:
        for line in cpuinfo.read_text(encoding="utf-8", errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model == "unknown CPU":
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    vectors = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    return f"{model}, {os.cpu_count() or 1} cores, {vectors}"


def _gpus() -> list[str]:
    if shutil.which("nvidia-smi") is None:
        return []
    listed = subprocess.run(
        ["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
        capture_output=True,
        text=True,
        check=False,
    )
    return [line.strip() for line in listed.stdout.splitlines() if line.strip()]


def machine() -> str:
    """This machine in words: the CPU (:func:`cpu_description`) and each GPU with its memory."""
    gpus = _gpus()
    return cpu_description() + (f"; {', '.join(gpus)}" if gpus else ", no GPU")


def table_from_markdown(markdown: str, summary: str, **extra: Any) -> Table:
    """A :class:`Table` from the first markdown table in ``markdown`` (what a benchmark prints),
    with ``summary`` and any of the optional keys (``title``, ``command``, ``figure``)."""
    lines: list[str] = []
    for line in markdown.splitlines():
        if line.strip().startswith("|"):
            lines.append(line.strip())
        elif lines:
            break
    if len(lines) < 2:
        raise ResultError("no markdown table to store")

    def cells(line: str) -> list[str]:
        return [cell.strip() for cell in line.strip("|").split(" | ")]

    table: dict[str, Any] = {
        "columns": cells(lines[0]),
        "rows": [cells(line) for line in lines[2:]],
    }
    table["summary"] = summary
    table.update(extra)
    return table  # type: ignore[return-value]


def _check_fields(
    where: str, found: dict[str, Any], required: dict[str, type], optional: dict[str, type]
) -> None:
    for key, kind in required.items():
        if key not in found:
            raise ResultError(f"{where}: no {key!r}")
        if not isinstance(found[key], kind) or isinstance(found[key], bool):
            raise ResultError(f"{where}: {key!r} is not a {kind.__name__}")
    for key, kind in optional.items():
        if key in found and not isinstance(found[key], kind):
            raise ResultError(f"{where}: {key!r} is not a {kind.__name__}")
    unknown = sorted(set(found) - set(required) - set(optional))
    if unknown:
        raise ResultError(f"{where}: unknown key {unknown[0]!r}")


def validate(found: object, where: str) -> Result:
    """``found`` as a :class:`Result`, or :class:`ResultError` naming the first fault."""
    if not isinstance(found, dict):
        raise ResultError(f"{where}: not a JSON object")
    _check_fields(where, found, _REQUIRED, _OPTIONAL)
    if not found["measures"] or not all(isinstance(p, str) and p for p in found["measures"]):
        raise ResultError(f"{where}: 'measures' must list the measured paths")
    if not found["tables"]:
        raise ResultError(f"{where}: no tables")
    for number, table in enumerate(found["tables"], 1):
        place = f"{where}: table {number}"
        if not isinstance(table, dict):
            raise ResultError(f"{place}: not a JSON object")
        _check_fields(place, table, _TABLE_REQUIRED, _TABLE_OPTIONAL)
        width = len(table["columns"])
        for row_number, row in enumerate(table["rows"], 1):
            if not isinstance(row, list) or len(row) != width:
                raise ResultError(f"{place}: row {row_number} does not have {width} cells")
            if not all(isinstance(cell, str) for cell in row):
                raise ResultError(f"{place}: row {row_number} has a cell that is not text")
        if "figure" in table:
            figure = table["figure"]
            if not isinstance(figure.get("path"), str) or not isinstance(
                figure.get("caption"), str
            ):
                raise ResultError(f"{place}: a figure needs a 'path' and a 'caption'")
    return found  # type: ignore[return-value]


def load(path: Path) -> Result:
    """The result in ``path``; :class:`ResultError` with one line if it cannot be read."""
    try:
        found = json.loads(path.read_text())
    except OSError as error:
        raise ResultError(f"{path}: {error.strerror}") from None
    except json.JSONDecodeError as error:
        raise ResultError(f"{path}: not JSON ({error.msg}, line {error.lineno})") from None
    return validate(found, str(path))


def write(
    name: str,
    *,
    title: str,
    order: int,
    command: str,
    measures: list[str],
    tables: list[Table],
    setup: str | None = None,
    data: list[str] | None = None,
    date: str | None = None,
    commit_hash: str | None = None,
    machine_name: str | None = None,
    folder: Path = TABLES,
    keep_summaries: bool = True,
) -> Path:
    """Write ``<folder>/<name>.json``, stamped with today's date, this commit and this machine
    unless they are given, and checked against the shape above before anything is written.
    ``keep_summaries=False`` writes the given summaries even where the stored table has the
    same columns and rows (a table rebuilt from its data, whose summary is the script's)."""
    result: dict[str, Any] = {
        "title": title,
        "order": order,
        "command": command,
        "date": date or datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
        "commit": commit_hash or commit(),
        "machine": machine_name or machine(),
        "measures": measures,
    }
    if setup is not None:
        result["setup"] = setup
    if data is not None:
        result["data"] = data
    path = folder / f"{name}.json"
    result["tables"] = _keeping_reviewed_summaries(tables, path) if keep_summaries else tables
    validate(result, str(path))
    folder.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2, ensure_ascii=False) + "\n")
    return path


def _keeping_reviewed_summaries(tables: list[Table], path: Path) -> list[Table]:
    """``tables``, each one whose columns and rows are those of the stored result's table at
    the same place taking that table's summary: a re-run that reproduces a table exactly
    (a learning result after a change that keeps every float) keeps the summary written for
    those very numbers, in place of the script's generic one."""
    try:
        stored = load(path)["tables"]
    except ResultError:  # none stored yet, or unreadable: the script's summaries
        return tables
    kept = []
    for given, old in zip(tables, stored, strict=False):
        same = (given["columns"], given["rows"]) == (old["columns"], old["rows"])
        kept.append({**given, "summary": old["summary"]} if same else given)
    return kept + tables[len(kept) :]


def span(values: Iterable[float], form: str = ".0f") -> str:
    """The least and the most of ``values`` formatted with ``form``, as "low–high", or one
    figure where both read the same."""
    listed = list(values)
    low, high = format(min(listed), form), format(max(listed), form)
    return low if low == high else f"{low}–{high}"


def command_line(module: str) -> str:
    """How this process was started, as a user types it: ``python -m <module> <arguments>``."""
    return shlex.join(["python", "-m", module, *sys.argv[1:]])


def _kept_fields(
    name: str, tables: list[Table], folder: Path, data: list[str] | None
) -> tuple[Result, dict[str, Any]]:
    """The stored result ``<folder>/<name>.json`` and what a new version of it keeps: its
    title, order, measured paths, set-up and data (unless ``data`` is given), with ``tables``
    in place of its own (a table given without a figure keeps the stored one's at its place)."""
    stored = load(folder / f"{name}.json")
    for given, old in zip(tables, stored["tables"], strict=False):
        if "figure" not in given and "figure" in old:
            given["figure"] = old["figure"]
    return stored, {
        "title": stored["title"],
        "order": stored["order"],
        "measures": stored["measures"],
        "tables": tables,
        "setup": stored.get("setup"),
        "data": data if data is not None else stored.get("data"),
        "folder": folder,
    }


def refresh(
    name: str,
    tables: list[Table],
    command: str,
    folder: Path = TABLES,
    data: list[str] | None = None,
) -> Path:
    """Replace the tables of the stored result ``<folder>/<name>.json`` with this run's,
    stamped now; its title, order, measured paths, set-up and data (unless ``data`` is given)
    stay. A table given without a figure keeps the stored table's figure at the same place."""
    _, kept = _kept_fields(name, tables, folder, data)
    return write(name, command=command, **kept)


def rerender(
    name: str,
    tables: list[Table],
    folder: Path = TABLES,
    stamps: dict[str, str] | None = None,
    data: list[str] | None = None,
) -> Path:
    """Replace the tables of the stored result ``<folder>/<name>.json`` with ones rebuilt now
    from the data it stores (a script's ``--tables-only``), keeping everything else: title,
    order, command, measured paths, set-up, data, and the date, commit and machine of the run
    the data was measured in (``stamps``: ``date``, ``commit`` and ``machine`` where the data
    file records them itself; ``data``: the files named, where given). The summaries are the
    script's, computed from that data; a table given without a figure keeps the stored
    table's figure at the same place."""
    stored, kept = _kept_fields(name, tables, folder, data)
    measured = stamps or stored
    return write(
        name,
        command=stored["command"],
        date=measured["date"],
        commit_hash=measured["commit"],
        machine_name=measured["machine"],
        keep_summaries=False,
        **kept,
    )
