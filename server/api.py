"""The Python API: run a federation from Python and load its trained policy back.

:func:`run` runs a federation in this process (the agents as plain objects, the reference the
distributed runtime reproduces bit for bit) or distributed (a server and K agent processes
forked as ``fedhpg-run`` does) and returns a :class:`RunResult`. :func:`load_policy` rebuilds a
run directory's policy with θ̃ of its newest valid checkpoint; :func:`act` and
:func:`evaluate` use it. Configuration mistakes raise :class:`ConfigError` (naming the key).
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fedhpg.common.config import ConfigError, RunConfig, from_dict, to_dict
from fedhpg.common.group import make_agent_group
from fedhpg.common.policies import Policy, get_flat_params, register_policy, set_flat_params
from fedhpg.common.registry import import_plugins
from fedhpg.common.runtime.cli import compose, validate_config
from fedhpg.common.types import EvaluationStats
from fedhpg.common.variants import run_variants, variant_of
from fedhpg.common.worker import build_policy, initial_theta
from fedhpg.envs.registry import register_family
from fedhpg.server.checkpoint import latest_valid_checkpoint, write_atomic
from fedhpg.server.coordinator import RoundCallback, RoundRecord, RunProgress
from fedhpg.server.metrics import (
    METRICS_SCHEMA_VERSION,
    MetricsWriter,
    read_metrics,
    tensorboard_sink,
)
from fedhpg.server.pools import FederationError
from fedhpg.server.pools.inprocess import run_in_process
from fedhpg.server.rounds import check_distributed_policy
from fedhpg.server.run_dir import RunDirectory, RunDirectoryError, claimed, holds_run
from fedhpg.server.strategies import make_strategy, validate_strategy

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
    """The run directory written, or None (in-process without ``out_dir``; distributed
    without one ran in a temporary directory, removed)."""
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
    ``config`` is None, else ``config`` with the overrides applied; checked like the CLI's."""
    if config is None:
        run_config = compose(list(overrides))
    else:
        if not isinstance(config, RunConfig):
            raise TypeError(f"config must be a RunConfig or None, got {type(config).__name__}")
        run_config = validate_config(_apply_overrides(config, overrides))
    validate_strategy(run_config)
    return run_config


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
    run_config = resolve_config(config, overrides)
    if out_dir is None and run_config.server.out_dir:
        out_dir = run_config.server.out_dir
    directory = Path(out_dir) if out_dir is not None else None
    if (run_config.resume or "").lower() == "auto":
        # As on the command line: resume the directory if it holds a run, else start.
        resumes = directory is not None and holds_run(directory)
        run_config = dataclasses.replace(run_config, resume="true" if resumes else None)
    if distributed:
        if callbacks:
            raise ValueError(
                "callbacks run in this process, so in-process runs only; a distributed run's "
                "rounds are in RunResult.records (and metrics.jsonl as they complete)"
            )
        return _run_distributed(run_config, directory)
    return _run_in_process(run_config, directory, list(callbacks))


# --- in-process ---------------------------------------------------------------------------------


class _Collect:
    def __init__(self) -> None:
        self.records: list[dict[str, Any]] = []
        self.last_round: int | None = None
        self.last_eval: dict[str, EvaluationStats] | None = None

    def __call__(self, record: RoundRecord, _: torch.Tensor) -> None:
        self.records.append({"schema": METRICS_SCHEMA_VERSION, **record.to_json()})
        if record.eval:
            self.last_round, self.last_eval = record.round, record.eval


def _run_in_process(
    run_config: RunConfig, directory: Path | None, callbacks: list[RoundCallback]
) -> RunResult:
    collect = _Collect()
    if directory is None:
        if run_config.resume:
            raise ConfigError("resume", "resuming needs the run directory: pass out_dir")
        theta = run_in_process(run_config, on_round=[collect, *callbacks])
        return RunResult(
            config=run_config,
            theta=theta,
            records=collect.records,
            out_dir=None,
            last_evaluation=collect.last_eval,
        )
    with claimed(directory, resume=bool(run_config.resume), key="out_dir") as run_dir:
        theta = _in_process_with_directory(run_config, run_dir, collect, callbacks)
    return RunResult(
        config=run_config,
        theta=theta,
        records=read_metrics(directory / "metrics.jsonl"),
        out_dir=directory,
        last_evaluation=collect.last_eval,
    )


def _in_process_with_directory(
    run_config: RunConfig,
    run_dir: RunDirectory,
    collect: _Collect,
    callbacks: list[RoundCallback],
) -> torch.Tensor:
    # The server's own pieces, so the directory is one fedhpg-server would have written (and
    # can resume).
    from fedhpg.server.main import checkpoint_callback, resume_point

    directory = run_dir.path
    theta: torch.Tensor | None = None
    progress = RunProgress()
    if run_config.resume:
        theta, progress, _ = resume_point(run_config, run_dir, make_strategy(run_config.strategy))
    write_atomic(directory / "config.json", json.dumps(to_dict(run_config), indent=2).encode())
    metrics = MetricsWriter(run_dir.metrics)
    start = theta if theta is not None else initial_theta(variant_of(run_config, 0), run_config)
    board = tensorboard_sink(
        run_config.server.tensorboard,
        directory,
        first_round=progress.next_round,
        theta=start,
        per_agent=run_config.agents.num_agents <= run_config.server.tensorboard_agents,
    )
    sinks: list[RoundCallback] = [
        metrics,
        checkpoint_callback(run_config, directory / "checkpoints", progress, dict),
        collect,
        *([board] if board is not None else []),
    ]
    try:
        theta = run_in_process(
            run_config, on_round=[*sinks, *callbacks], theta=start, progress=progress
        )
    finally:
        metrics.close()
        if board is not None:
            board.close()
    variants = run_variants(run_config)
    summary = {
        "rounds": run_config.rounds,
        "final_eval_round": collect.last_round,
        "eval": {a: e.to_json() for a, e in collect.last_eval.items()}
        if collect.last_eval
        else None,
        "variants": {f"agent-{k}": {"gamma": v.gamma, **v.params} for k, v in enumerate(variants)},
    }
    write_atomic(directory / "summary.json", json.dumps(summary, indent=2).encode())
    return theta


# --- distributed --------------------------------------------------------------------------------


def _run_distributed(run_config: RunConfig, directory: Path | None) -> RunResult:
    from fedhpg.common.engine.devices import check_device_before_fork
    from fedhpg.common.wire.security import check_launch_keys
    from fedhpg.server.launcher import run_federation

    check_launch_keys(run_config)
    check_device_before_fork(run_config)  # the agents are forked from this process
    check_distributed_policy(run_config)
    # What the server would refuse in its own process (exit 2): found here, as an exception.
    initial_theta(variant_of(run_config, 0), run_config)
    with tempfile.TemporaryDirectory(prefix="fedhpg-run-") as scratch:
        where = directory if directory is not None else Path(scratch) / "run"
        if run_config.resume and run_config.resume.lower() != "true":
            where = Path(run_config.resume)  # the launcher resumes that directory
        forked = dataclasses.replace(
            run_config, server=dataclasses.replace(run_config.server, out_dir=str(where))
        )
        status = run_federation(forked)
        if status == 130:
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
            out_dir=directory,
            last_evaluation={a: EvaluationStats(**e) for a, e in summary["eval"].items()}
            if summary.get("eval")
            else None,
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


def load_policy(run_dir: str | Path) -> Policy:
    """The run's policy (a ``torch.nn.Module``) with θ̃ of its newest valid checkpoint.

    Built for the run's spaces from ``run_dir/config.json`` (its plugins imported first). Act
    with :func:`act`, or for batches ``policy.act(obs[B, ...], noise)`` (``noise`` [B,
    policy.noise_size] uniforms in [0, 1), None for the greedy actions);
    ``policy.log_prob(obs, actions)`` is differentiable.
    """
    config = load_run_config(run_dir)
    checkpoint = latest_valid_checkpoint(Path(run_dir) / "checkpoints")
    if checkpoint is None:
        raise RunDirectoryError(f"no valid checkpoint in {Path(run_dir) / 'checkpoints'}")
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
