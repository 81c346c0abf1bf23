"""``--help`` of the entry points, generated at help time from the config itself: the
docstring under each field of :mod:`fedhpg.common.configuration.config` and its sections
(:mod:`fedhpg.common.configuration.settings`, read with ``ast``), the defaults of
the composed ``conf/config.yaml`` and the config groups in ``conf/``. New fields, groups and
options appear by themselves."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import shutil
import textwrap
import typing
from typing import Any

from fedhpg.common.configuration import config as config_module
from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.run_keys import flatten
from fedhpg.common.configuration.settings import (
    agent,
    agents,
    algo,
    attack,
    cluster,
    env,
    policy,
    privacy,
    server,
    strategy,
)
from fedhpg.common.runtime.composition import hydra_context

USAGE = {
    "fedhpg-run": "[-m] [group=option ...] [key=value ...]",
    "fedhpg-server": "[key=value ...]",
    "fedhpg-agent": "agent.index=K [key=value ...]",
    "fedhpg-cluster": "[cluster=local|slurm|ray] [cluster.key=value ...] [key=value ...]",
}
WHAT = {
    "fedhpg-run": "Run a whole federation on this machine: one server and K agent processes.",
    "fedhpg-server": "Run the server of a federation: bind, wait for K agents, run the rounds.",
    "fedhpg-agent": "Run one agent of a federation: connect to the server, train when asked.",
    "fedhpg-cluster": "Place a federation on a cluster engine (SLURM, Ray): the server one job, "
    "the agents a job array.",
}
EXAMPLES = {
    "fedhpg-run": [
        "fedhpg-run rounds=20 seed=3 algo=fedhpgvr",
        "fedhpg-run env=cartpole agents=homogeneous4 server.port=5601",
        "fedhpg-run -m seed=0,1,2 algo.step_size=0.5,1.0  # a sweep",
        "fedhpg-run env=gym env.id=MountainCar-v0 '+env.vary.force={spread: 0.5}'",
        "fedhpg-run resume=runs/DIR rounds=80  # continue a run",
    ],
    "fedhpg-server": [
        "fedhpg-server server.port=5555 server.out_dir=runs/manual",
        "fedhpg-server resume=true server.out_dir=runs/manual rounds=80",
    ],
    "fedhpg-agent": ["fedhpg-agent agent.index=0 server.host=127.0.0.1 server.port=5555"],
    "fedhpg-cluster": [
        "fedhpg-cluster cluster=local rounds=20  # the same jobs as processes on this machine",
        "fedhpg-cluster cluster=slurm cluster.partition=cpu cluster.time_min=120 "
        "server.out_dir=/shared/runs/a",
        "fedhpg-cluster cluster=ray cluster.address=head:6379 server.out_dir=/shared/runs/b",
    ],
}
OWN_SECTIONS = {"cluster": "fedhpg-cluster"}
"""Config sections that only one program reads: listed in its help alone."""
KEY_COLUMN = 40
WIDTHS = (60, 120)
"""The narrowest and widest help: the terminal's width (``COLUMNS``) within these."""
MORE = (
    "More: docs/configuration.md (every key and group), docs/running.md (running, resuming, "
    "what a run writes); the documentation site: make docs."
)


def line_width() -> int:
    """The terminal's width (``COLUMNS`` where set), within :data:`WIDTHS`."""
    columns = shutil.get_terminal_size((100, 24)).columns
    return min(max(columns, WIDTHS[0]), WIDTHS[1])


def _entry(left: str, doc: str, width: int) -> list[str]:
    """A key and its description, wrapped at words into a column beside it (below it when the
    key is wider than the column): nothing is cut."""
    column = KEY_COLUMN if width - KEY_COLUMN >= 30 else 8
    if not doc:
        return [left]
    lines = textwrap.wrap(doc, width - column - 2, break_long_words=False, break_on_hyphens=False)
    pad = " " * (column + 2)
    if len(left) > column:
        return [left, *(pad + line for line in lines)]
    return [f"{left:<{column}}  {lines[0]}", *(pad + line for line in lines[1:])]


SECTION_MODULES = (env, algo, strategy, agents, attack, policy, server, agent, privacy, cluster)
"""The modules of the config's sections, whose field docstrings ``--help`` shows."""


def field_docs() -> dict[str, dict[str, str]]:
    """``{class name: {field: first sentence of its docstring}}`` for every config dataclass."""
    docs: dict[str, dict[str, str]] = {}
    nodes = [
        node
        for module in (config_module, *SECTION_MODULES)
        for node in ast.parse(inspect.getsource(module)).body
    ]
    for node in nodes:
        if not isinstance(node, ast.ClassDef):
            continue
        fields = docs.setdefault(node.name, {})
        for current, following in zip(node.body, node.body[1:], strict=False):
            if (
                isinstance(current, ast.AnnAssign)
                and isinstance(current.target, ast.Name)
                and isinstance(following, ast.Expr)
                and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)
            ):
                fields[current.target.id] = _first_sentence(following.value.value)
    return docs


def _first_sentence(text: str) -> str:
    """The docstring's first sentence (a period before a capital), on one line."""
    text = " ".join(text.replace("``", "").split())
    first = re.split(r"(?<!e\.g)(?<!i\.e)(?<=[a-z0-9)'\]])\. (?=[A-Z])", text, maxsplit=1)[0]
    return first.rstrip(".")


def _key_docs() -> dict[str, str]:
    """Dotted key → doc, following RunConfig's nested dataclasses."""
    docs = field_docs()
    keyed: dict[str, str] = {}
    hints = typing.get_type_hints(RunConfig)
    for top in dataclasses.fields(RunConfig):
        nested = hints[top.name]
        if isinstance(nested, type) and dataclasses.is_dataclass(nested):
            for inner in dataclasses.fields(nested):
                keyed[f"{top.name}.{inner.name}"] = docs.get(nested.__name__, {}).get(
                    inner.name, ""
                )
        else:
            keyed[top.name] = docs["RunConfig"].get(top.name, "")
    return keyed


def _defaults() -> tuple[dict[str, Any], dict[str, list[str]], dict[str, str]]:
    """The composed default config's leaves, each config group's options and default."""
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    with hydra_context():
        loader = GlobalHydra.instance().config_loader()
        groups = {
            name: loader.get_group_options(name)
            for name in loader.list_groups("")
            if name != "hydra"
        }
        from hydra import compose

        cfg = compose(config_name="config", return_hydra_config=True)
    chosen = {str(k): str(v) for k, v in cfg.hydra.runtime.choices.items()}
    values = OmegaConf.to_container(cfg)
    assert isinstance(values, dict)
    values.pop("hydra")
    return flatten(values), groups, chosen


def help_text(program: str, width: int | None = None) -> str:
    """The help of ``program``, at most ``width`` columns (default: :func:`line_width`); only a
    key's default longer than that runs past it."""
    width = line_width() if width is None else width
    values, groups, chosen = _defaults()
    about = (
        f"{WHAT.get(program, '')} Settings are Hydra overrides of conf/config.yaml, typed by "
        "fedhpg.common.configuration.config. A bad value is one line on stderr and exit status "
        "2; nothing is started."
    )
    lines = [
        f"usage: {program} {USAGE.get(program, '[key=value ...]')}",
        "",
        *textwrap.wrap(about, width, break_long_words=False, break_on_hyphens=False),
        "",
        "config groups (group=option):",
    ]
    for name, options in sorted(groups.items()):
        if OWN_SECTIONS.get(name, program) != program:
            continue
        marked = [f"{o} (default)" if o == chosen.get(name) else o for o in options]
        lines += _group_entry(name, marked, width)
    lines += ["", "keys (key=value; default, then what it is):"]
    section = ""
    for key, doc in _key_docs().items():
        if OWN_SECTIONS.get(key.split(".")[0], program) != program:
            continue
        if "." in key and key.split(".")[0] != section:
            section = key.split(".")[0]
            lines.append(f" {section}.*")
        lines += _entry(f"  {key}={_short(_value(values, key))}", doc, width)
    lines += ["", "examples:"]
    for example in EXAMPLES.get(program, []):
        lines += textwrap.wrap(
            example,
            width,
            initial_indent="  ",
            subsequent_indent="      ",
            break_long_words=False,
            break_on_hyphens=False,
        )
    lines += ["", *textwrap.wrap(MORE, width, break_long_words=False, break_on_hyphens=False)]
    return "\n".join(lines) + "\n"


def _group_entry(name: str, options: list[str], width: int) -> list[str]:
    head = f"  {name + '=':<12} "
    wrapped = textwrap.wrap(
        ", ".join(options),
        width - len(head),
        break_long_words=False,
        break_on_hyphens=False,
    )
    return [head + wrapped[0], *(" " * len(head) + line for line in wrapped[1:])]


def _value(leaves: dict[str, Any], key: str) -> Any:
    """A key's default; a dict key (e.g. agents.budget) is gathered from its leaves."""
    if key in leaves:
        return leaves[key]
    inner = {k[len(key) + 1 :]: v for k, v in leaves.items() if k.startswith(key + ".")}
    return inner or None


def _short(value: Any) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_short(v)}" for k, v in value.items()) + "}"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)
