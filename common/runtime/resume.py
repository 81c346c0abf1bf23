"""Resume from a run directory: its ``config.json`` is the config, the command line's
overrides apply on top, and a change to a key the run must keep is refused naming it."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fedhpg.common.configuration.config import RunConfig, to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.run_keys import fixed_difference, flatten
from fedhpg.common.runtime.composition import NO_RESUME, compose_cfg, hydra_errors, to_run_config
from fedhpg.common.runtime.run_files import holds_run


def settle_auto(overrides: Sequence[str]) -> list[str]:
    """``resume=auto``, for a server that a supervisor restarts with the same command (compose's
    ``restart: on-failure``): ``resume=true`` when ``server.out_dir`` holds a run, otherwise a
    fresh start. Every other override is kept as it is."""
    if (resume_value(overrides) or "").lower() != "auto":
        return list(overrides)
    out_dirs = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == "server.out_dir"]
    if not out_dirs:
        raise ConfigError("resume", "resume=auto needs server.out_dir=DIR")
    settled = "resume=true" if holds_run(Path(out_dirs[-1])) else "resume=null"
    return [o for o in overrides if o.split("=", 1)[0].lstrip("+") != "resume"] + [settled]


def resume_value(overrides: Sequence[str]) -> str | None:
    values = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0].lstrip("+") == "resume"]
    return values[-1] if values and values[-1].strip().lower() not in NO_RESUME else None


def resume_directory(overrides: Sequence[str]) -> Path:
    """``resume=DIR``, or ``resume=true`` with ``server.out_dir=DIR``."""
    value = resume_value(overrides)
    assert value is not None
    if value.lower() != "true":
        return Path(value)
    out_dirs = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == "server.out_dir"]
    if not out_dirs:
        raise ConfigError("resume", "resume=true needs server.out_dir=DIR (or give resume=DIR)")
    return Path(out_dirs[-1])


def run_config_file(directory: Path) -> dict[str, Any]:
    """A run directory's ``config.json``, the run's resolved config."""
    path = directory / "config.json"
    try:
        values = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        what = "no such directory" if not directory.is_dir() else "it has no config.json"
        raise ConfigError("resume", f"{directory}: {what}; not a fedhpg run directory") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ConfigError("resume", f"cannot read {path}: {error}") from None
    if not isinstance(values, dict):
        raise ConfigError("resume", f"{path} is not a fedhpg config")
    return values


def compose_resume(overrides: list[str]) -> RunConfig:
    """The run's ``config.json``; then each config group named on the command line sets what
    that group sets, and each key override applies on top (Hydra's own override rules). A
    change to a key that a resume must keep (``GROUPS`` fixed) is refused naming it."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import DictConfig, OmegaConf

    directory = resume_directory(overrides)
    before = run_config_file(directory)
    loader = GlobalHydra.instance().config_loader()
    group_names = set(loader.list_groups(""))
    with hydra_errors(overrides):
        parsed = OverridesParser.create(config_loader=loader).parse_overrides(overrides)
        cfg = OmegaConf.merge(OmegaConf.structured(RunConfig), before)
        assert isinstance(cfg, DictConfig)
        defaults = flatten(OmegaConf.to_container(compose_cfg([])))
        for override in parsed:
            if override.key_or_group.split("/")[0] in group_names:
                line = f"{override.get_key_element()}={override.get_value_element_as_str()}"
                chosen = flatten(OmegaConf.to_container(compose_cfg([line])))
                for key, value in chosen.items():
                    if defaults.get(key) != value:
                        OmegaConf.update(cfg, key, value, merge=False, force_add=True)
        keys = [
            o
            for o in parsed
            if o.key_or_group.split("/")[0] not in group_names
            and not o.key_or_group.startswith("hydra.")
        ]
        ConfigLoaderImpl._apply_overrides_to_config(keys, cfg)
    run = to_run_config(cfg)
    changed = fixed_difference(before, to_dict(run))
    if changed is not None:
        raise ConfigError(changed.key, f"{str(changed).split(': ', 1)[1]} (resuming {directory})")
    return run
