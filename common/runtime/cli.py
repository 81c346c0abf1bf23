"""Entry-point plumbing: compose the Hydra config, validate it once, report user errors briefly."""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Sequence

from fedhpg.common.config import ConfigError, RunConfig

logger = logging.getLogger(__name__)

CONFIG_MODULE = "fedhpg.conf"
CONFIG_NAME = "config"
SCHEMA_NAME = "run_schema"
EXIT_USAGE = 2


def register_schema() -> None:
    """Make ``RunConfig`` the schema that ``conf/config.yaml`` extends (Hydra ConfigStore)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=SCHEMA_NAME, node=RunConfig)


def to_run_config(cfg: object) -> RunConfig:
    """DictConfig → validated RunConfig; OmegaConf type errors become ConfigError."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    assert isinstance(cfg, DictConfig)
    try:
        config = OmegaConf.to_object(cfg)
    except OmegaConfBaseException as error:
        raise ConfigError(
            str(getattr(error, "full_key", "") or "config"), _first_line(error)
        ) from None
    if not isinstance(config, RunConfig):
        raise ConfigError("config", "the composed config is not a fedhpg run config")
    return validate_config(config)


def validate_config(config: RunConfig) -> RunConfig:
    """Every check a process can make of its own config: values, plugins, the algorithm and
    budgets, the key files it names. (The server also checks ``strategy``.)"""
    from fedhpg.common.components import validate_run
    from fedhpg.common.wire.security import validate_security

    validate_run(config)
    validate_security(config.security)
    return config


def _first_line(error: BaseException) -> str:
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__


def _one_line(error: BaseException) -> str:
    """Hydra puts the useful part ("could not be converted to Float") on later lines."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    noise = ("full_key", "object_type", "reference_type", "Set the")
    useful = [line for line in lines if not line.startswith(noise)]
    return "; ".join(useful[:2]) if useful else type(error).__name__


def compose(overrides: Sequence[str]) -> RunConfig:
    """Compose ``conf/config.yaml`` with command-line overrides, without Hydra's run dirs."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import OmegaConfBaseException

    register_schema()
    try:
        with initialize_config_module(config_module=CONFIG_MODULE, version_base=None):
            cfg = hydra_compose(config_name=CONFIG_NAME, overrides=list(overrides))
    except MissingConfigException as error:
        key = _override_key(error, overrides)
        options = getattr(error, "options", None) or []
        chosen = next((o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == key), "?")
        raise ConfigError(
            key, f"no such option {chosen!r}; allowed: {', '.join(options)}"
        ) from None
    except (HydraException, OmegaConfBaseException) as error:
        cause = error.__cause__ if isinstance(error.__cause__, OmegaConfBaseException) else error
        key = getattr(cause, "full_key", None) or _override_key(error, overrides)
        if "To append to your config use +" in str(error):
            raise ConfigError(
                key,
                f"not in the composed config; add it with +{key}=... (an algorithm's budget and "
                "options come with its group: algo=NAME)",
            ) from None
        raise ConfigError(key, _one_line(cause)) from None
    return to_run_config(cfg)


def _override_key(error: BaseException, overrides: Sequence[str]) -> str:
    """The override a Hydra error is about, when its message names one."""
    text = str(error)
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if key and key in text:
            return key
    return "overrides"


def setup_logging(level: str | int = "INFO") -> None:
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )


def limit_threads() -> None:
    """One thread for torch/OMP: K agent processes share two cores, more threads thrash."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


def run_entry(main: Callable[[RunConfig], int], argv: Sequence[str] | None = None) -> int:
    """Compose, validate and run ``main``; user mistakes exit 2 with one line, never a trace."""
    args = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help") for a in args):
        program = os.path.basename(sys.argv[0])
        sys.stdout.write(
            f"usage: {program} [key=value ...]\n"
            "Hydra overrides of conf/config.yaml, e.g. agents.num_agents=3 rounds=20 seed=1\n"
        )
        return 0
    setup_logging(os.environ.get("FEDHPG_LOG_LEVEL", "INFO"))
    try:
        run = compose(args)
    except ConfigError as error:
        sys.stderr.write(f"error: {error}\n")
        return EXIT_USAGE
    limit_threads()
    try:
        return main(run)
    except ConfigError as error:
        sys.stderr.write(f"error: {error}\n")
        return EXIT_USAGE
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        return 130
