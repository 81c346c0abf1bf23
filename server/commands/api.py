"""The Python API: run a federation from Python and load its trained policy back.

:func:`run` runs a federation in this process (the agents as plain objects, the reference the
distributed runtime reproduces bit for bit) or distributed (a server and K agent processes
forked as ``fedhpg-run`` does) and returns a :class:`RunResult`. :func:`load_policy` rebuilds a
run directory's policy with θ̃ of its newest valid checkpoint; :func:`act` and
:func:`evaluate` use it. Configuration mistakes raise :class:`ConfigError` (naming the key).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fedhpg.common.configuration.config import RunConfig, from_dict, to_dict
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.registry import import_plugins
from fedhpg.common.heterogeneity.variants import variant_of
from fedhpg.common.learning.engine.devices import check_device_before_fork
from fedhpg.common.learning.group import make_agent_group
from fedhpg.common.learning.policies import (
    Policy,
    get_flat_params,
    register_policy,
    set_flat_params,
)
from fedhpg.common.learning.worker import build_policy
from fedhpg.common.records.types import EvaluationStats
from fedhpg.common.runtime.cli import compose, validate_config
from fedhpg.common.wire.security import check_launch_keys
from fedhpg.envs.registry import register_family
from fedhpg.server.assembly import CheckedRun, assemble, check_run
from fedhpg.server.checkpoint import CheckpointError, best_checkpoint, latest_valid_checkpoint
from fedhpg.server.commands.launcher import prepare_compiled_engine, run_federation
from fedhpg.server.coordinator import RoundCallback, RoundRecord
from fedhpg.server.metrics import metrics_line, read_metrics, record_marks
from fedhpg.server.pools import FederationError
from fedhpg.server.pools.inprocess import make_in_process_pool
from fedhpg.server.report import evaluation_of
from fedhpg.server.run_dir import RunDirectoryError, claimed, holds_run, new_run_dir
from fedhpg.server.serving import message_cap

__all__ = [
    "ConfigError",
    "FederationError",
    "Policy",
    "RoundRecord",
    "RunConfig",
    "RunDirectoryError",
    "RunResult",
    "act",
    "compose",
    "evaluate",
    "load_policy",
    "load_run_config",
    "register_family",
    "register_policy",
    "run",
]


@dataclass(frozen=True, kw_only=True)
class RunResult:
    """What :func:`run` returns."""

    config: RunConfig
    """The validated configuration the federation ran."""
    theta: torch.Tensor
    """θ̃_T, the final unified policy's flat parameter vector."""
    records: list[dict[str, Any]]
    """One dict per round, exactly the lines of ``metrics.jsonl`` (schema: docs/metrics.md),
    in both modes; a resumed run's include the rounds before the resume."""
    out_dir: Path | None
    """The run directory written: ``out_dir``, or for a distributed run without one a new
    ``runs/<date>-<time>-<env>-<algo>`` (kept); None in-process without ``out_dir``."""
    last_evaluation: dict[str, EvaluationStats] | None
    """Agent id → the unified policy's evaluation after the last round."""


def _apply_overrides(config: RunConfig, overrides: Sequence[str]) -> RunConfig:
    """``key=value`` pairs on a config object (OmegaConf dot-list syntax; a leading ``+``
    is accepted, since a config object holds every key already)."""
    if not overrides:
        return config
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    for override in overrides:
        if "=" not in override:
            raise ConfigError("overrides", f"{override!r} is not key=value")
    try:
        values = OmegaConf.to_container(OmegaConf.from_dotlist([o.lstrip("+") for o in overrides]))
    except OmegaConfBaseException as error:
        raise ConfigError("overrides", str(error).splitlines()[0]) from None
    assert isinstance(values, dict)
    merged = OmegaConf.merge(OmegaConf.create(to_dict(config)), values)
    return from_dict(OmegaConf.to_container(merged))  # type: ignore[arg-type]


def resolve_config(config: RunConfig | None = None, overrides: Sequence[str] = ()) -> RunConfig:
    """The config a run takes: ``conf/config.yaml`` composed with Hydra ``overrides`` when
    ``config`` is None, else ``config`` with the overrides applied; checked like the CLI's,
    and as its server checks it (:func:`~fedhpg.server.assembly.check_run`)."""
    return _checked(config, overrides, distributed=False).run


def _checked(
    config: RunConfig | None, overrides: Sequence[str], *, distributed: bool
) -> CheckedRun:
    if config is None:
        run_config = compose(list(overrides))
    else:
        if not isinstance(config, RunConfig):
            raise TypeError(f"config must be a RunConfig or None, got {type(config).__name__}")
        run_config = validate_config(_apply_overrides(config, overrides))
    return check_run(run_config, distributed=distributed)


def run(
    config: RunConfig | None = None,
    *,
    overrides: Sequence[str] = (),
    distributed: bool = False,
    out_dir: str | Path | None = None,
    callbacks: Sequence[RoundCallback] = (),
) -> RunResult:
    """Run one federation and return θ̃, the round records and the last evaluation.

    ``callbacks`` are called after every round with the typed :class:`RoundRecord` and θ̃ (in
    this process, so in-process runs only). ``out_dir`` (default: ``server.out_dir``, else
    none): write the run directory there (metrics.jsonl, config.json, summary.json,
    checkpoints/, tensorboard/), as the server does.
    """
    checked = _checked(config, overrides, distributed=distributed)
    run_config = checked.run
    if out_dir is None and run_config.server.out_dir:
        out_dir = run_config.server.out_dir
    directory = Path(out_dir) if out_dir is not None else None
    if (run_config.resume or "").lower() == "auto":
        # As on the command line: resume the directory if it holds a run, else start.
        resumes = directory is not None and holds_run(directory)
        run_config = dataclasses.replace(run_config, resume="true" if resumes else None)
        checked = dataclasses.replace(checked, run=run_config)
    if distributed:
        if callbacks:
            raise ValueError(
                "callbacks run in this process, so in-process runs only; a distributed run's "
                "rounds are in RunResult.records (and metrics.jsonl as they complete)"
            )
        return _run_distributed(checked, directory)
    return _run_in_process(checked, directory, list(callbacks))


# --- in-process ---------------------------------------------------------------------------------


class _Records:
    def __init__(self, run: RunConfig) -> None:
        self.records: list[dict[str, Any]] = []
        self.marks = record_marks(run)

    def __call__(self, record: RoundRecord, _: torch.Tensor) -> None:
        self.records.append(metrics_line(record, self.marks))


def _run_in_process(
    checked: CheckedRun, directory: Path | None, callbacks: list[RoundCallback]
) -> RunResult:
    """The run with its agents in this process: assembled as the server assembles its own, so
    a run directory written here is one fedhpg-server would have written (and can resume)."""
    run_config = checked.run
    if directory is None and run_config.resume:
        raise ConfigError("resume", "resuming needs the run directory: pass out_dir")

    prepare_compiled_engine(run_config)  # says so when numba compiles (the first run: ~20 s)
    records = _Records(run_config)
    with contextlib.ExitStack() as stack:
        run_dir = None
        if directory is not None:
            run_dir = stack.enter_context(
                claimed(directory, resume=bool(run_config.resume), key="out_dir")
            )
        assembly = assemble(checked, run_dir=run_dir, callbacks=[records, *callbacks])
        pool = make_in_process_pool(run_config)
        try:
            theta = assembly.run_rounds(pool)
        finally:
            pool.close()
            assembly.close()
        assembly.finish(pool.agent_ids)
    return RunResult(
        config=run_config,
        theta=theta,
        records=read_metrics(directory / "metrics.jsonl") if directory else records.records,
        out_dir=directory,
        last_evaluation=assembly.last.eval,
    )


# --- distributed --------------------------------------------------------------------------------


def _run_distributed(checked: CheckedRun, directory: Path | None) -> RunResult:
    # What the server would refuse in its own process (exit 2): found here, as an exception.
    run_config = checked.run
    message_cap(run_config, int(checked.initial_theta.numel()))
    check_launch_keys(run_config)
    check_device_before_fork(run_config)  # the agents are forked from this process
    where = directory if directory is not None else new_run_dir(run_config)
    if run_config.resume and run_config.resume.lower() != "true":
        where = Path(run_config.resume)  # the launcher resumes that directory
    forked = dataclasses.replace(
        run_config, server=dataclasses.replace(run_config.server, out_dir=str(where))
    )
    status = run_federation(forked)
    if status in (130, 143):  # SIGINT, SIGTERM
        raise KeyboardInterrupt
    if status != 0:
        raise FederationError(
            f"the federation exited with status {status} (its processes' log says why); "
            f"run directory: {where}"
        )
    checkpoint = latest_valid_checkpoint(where / "checkpoints")
    if checkpoint is None:
        raise FederationError(f"the federation left no valid checkpoint in {where}")
    summary = json.loads((where / "summary.json").read_text(encoding="utf-8"))
    return RunResult(
        config=run_config,
        theta=checkpoint.theta,
        records=read_metrics(where / "metrics.jsonl"),
        out_dir=where,
        last_evaluation=evaluation_of(summary["eval"]) if summary.get("eval") else None,
    )


# --- a trained policy ---------------------------------------------------------------------------


def load_run_config(run_dir: str | Path) -> RunConfig:
    """The run's config (``run_dir/config.json``), its plugins imported."""
    path = Path(run_dir) / "config.json"
    try:
        values = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise RunDirectoryError(f"cannot read the run's config {path}: {error}") from None
    config = from_dict(values)
    import_plugins(config.plugins)
    return config


def load_policy(run_dir: str | Path, *, best: bool = False) -> Policy:
    """The run's policy (a ``torch.nn.Module``) with θ̃ of its newest valid checkpoint, or with
    ``best`` of its best evaluation's (a run with ``checkpoint.keep_best=true``).

    Built for the run's spaces from ``run_dir/config.json`` (its plugins imported first). Act
    with :func:`act`, or for batches ``policy.act(obs[B, ...], noise)`` (``noise`` [B,
    policy.noise_size] uniforms in [0, 1), None for the greedy actions);
    ``policy.log_prob(obs, actions)`` is differentiable.
    """
    config = load_run_config(run_dir)
    directory = Path(run_dir) / "checkpoints"
    if best:
        try:
            checkpoint = best_checkpoint(directory)
        except CheckpointError as error:
            raise RunDirectoryError(str(error)) from None
        if checkpoint is None:
            raise RunDirectoryError(
                f"no best checkpoint in {directory} (the run needs checkpoint.keep_best=true)"
            )
    else:
        checkpoint = latest_valid_checkpoint(directory)
        if checkpoint is None:
            raise RunDirectoryError(f"no valid checkpoint in {directory}")
    policy = build_policy(variant_of(config, 0), config)
    set_flat_params(policy, checkpoint.theta)
    return policy


def act(
    policy: Policy,
    observation: Any,
    *,
    greedy: bool = True,
    rng: np.random.Generator | None = None,
) -> Any:
    """One action for one observation: greedy (argmax / mean) or sampled with ``rng``."""
    if not greedy and rng is None:
        raise ValueError("a sampled action needs rng (a numpy Generator)")
    batch = torch.as_tensor(np.asarray(observation))[None, ...]
    noise = None if greedy else torch.from_numpy(rng.random((1, policy.noise_size)))  # type: ignore[union-attr]
    with torch.no_grad():
        action = policy.act(batch, None if noise is None else noise.float())[0].numpy()
    return action.item() if np.ndim(action) == 0 else action


def evaluate(
    policy: Policy,
    run_dir: str | Path,
    agent: int,
    *,
    round: int | None = None,
    episodes: int | None = None,
) -> EvaluationStats:
    """``policy`` evaluated in agent ``agent``'s environment exactly as the run's server
    evaluates: the same episodes, horizon, greedy setting and random streams of ``round``
    (default: the run's last round, which is always evaluated)."""
    config = load_run_config(run_dir)
    if not 0 <= agent < config.agents.num_agents:
        raise ValueError(f"agent must be in [0, {config.agents.num_agents}), got {agent!r}")
    # through the group the run's agents evaluate with: the compiled, numpy and loop engines
    # draw their episodes' random numbers differently
    group = make_agent_group(config, [agent])
    try:
        return group.evaluate(
            config.rounds if round is None else round,
            get_flat_params(policy),
            episodes or config.eval.episodes,
            [agent],
        )[agent]
    finally:
        group.close()
