"""The batched engines: many agents of one run sampled, evaluated and differentiated together.

:func:`batched_group_or_none` returns an engine for the run when one supports the run's
algorithm, policy and environment family, else None (the caller loops over LocalWorkers):
with ``algo.engine=auto`` the compiled engine (:mod:`.compiled`, numba: CartPole) where it
applies, else the numpy engine (:mod:`.engine`: any family); ``algo.engine=numpy`` always the
numpy engine.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from fedhpg.common.batched.mlp import MLPShape
from fedhpg.common.config import RunConfig
from fedhpg.envs.base import EnvVariant

if TYPE_CHECKING:
    from fedhpg.common.group import AgentGroup
    from fedhpg.common.policies import Policy


def _unsupported(run: RunConfig, policy: Policy) -> str | None:
    from fedhpg.common.policies import MLPCategoricalPolicy

    if run.algo.name != "fedhpg":
        return f"algorithm {run.algo.name!r} (the engine runs fedhpg)"
    if run.algo.optimizer not in ("sgd", "adam"):
        return f"optimizer {run.algo.optimizer!r}"
    if type(policy) is not MLPCategoricalPolicy:
        return f"policy {type(policy).__name__} (the engine runs MLPCategoricalPolicy)"
    return None


def _policy(run: RunConfig, variants: Mapping[int, EnvVariant]) -> Policy:
    from fedhpg.common.worker import build_policy

    return build_policy(variants[min(variants)], run)


def unsupported(run: RunConfig, variants: Mapping[int, EnvVariant]) -> str | None:
    """Why the batched engine cannot train this run (None: it can)."""
    return _unsupported(run, _policy(run, variants))


def mlp_shape(policy: Policy) -> MLPShape:
    from torch import nn

    assert isinstance(policy, nn.Module)
    linear = [m for m in policy.modules() if isinstance(m, nn.Linear)]
    return MLPShape((linear[0].in_features, *(m.out_features for m in linear)))


def uses_compiled_engine(run: RunConfig) -> bool:
    """Whether the run's agents train on the compiled engine (so a launcher can compile or
    load its kernels once, before it forks them)."""
    if run.algo.engine != "auto":
        return False
    from fedhpg.common.variants import variants_of

    variants = variants_of(run, [0])
    if unsupported(run, variants) is not None:
        return False
    from fedhpg.common.batched.compiled import compiled_unsupported

    return compiled_unsupported(run, variants) is None


def batched_group_or_none(run: RunConfig, variants: Mapping[int, EnvVariant]) -> AgentGroup | None:
    """The batched engine for these agents, or None where it does not apply."""
    if run.algo.engine == "loop":
        return None
    policy = _policy(run, variants)  # one env, for the spaces
    if _unsupported(run, policy) is not None:
        return None
    if run.algo.engine == "auto":
        # imported here: numba's import and compilation are paid only by runs that use it
        from fedhpg.common.batched.compiled import CompiledFedHPG, compiled_unsupported

        if compiled_unsupported(run, variants) is None:
            return CompiledFedHPG(run, variants, mlp_shape(policy))
    from fedhpg.common.batched.engine import BatchedFedHPG

    return BatchedFedHPG(run, variants, mlp_shape(policy))
