"""The compiled CartPole backend (numba): FedHPG for CartPole agents with the MLP categorical
policy, each local iteration of all of them in two kernel calls.

:func:`batched_group_or_none` returns it where it applies (``algo.engine=auto``, FedHPG, the
MLP categorical policy, CartPole variants); everything else trains on the engine
(:mod:`fedhpg.common.engine`).
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
    from fedhpg.common.algorithms.fedhpg import FedHPG
    from fedhpg.common.components import resolve_algorithm
    from fedhpg.common.policies import MLPCategoricalPolicy

    if type(resolve_algorithm(run)[0]) is not FedHPG:
        return f"algorithm {run.algo.name!r} (the compiled backend runs fedhpg)"
    if run.algo.optimizer not in ("sgd", "adam"):
        return f"optimizer {run.algo.optimizer!r}"
    if type(policy) is not MLPCategoricalPolicy:
        return f"policy {type(policy).__name__} (the compiled backend runs MLPCategoricalPolicy)"
    return None


def _policy(run: RunConfig, variants: Mapping[int, EnvVariant]) -> Policy:
    from fedhpg.common.worker import build_policy

    return build_policy(variants[min(variants)], run)


def mlp_shape(policy: Policy) -> MLPShape:
    from torch import nn

    assert isinstance(policy, nn.Module)
    linear = [m for m in policy.modules() if isinstance(m, nn.Linear)]
    return MLPShape((linear[0].in_features, *(m.out_features for m in linear)))


def uses_compiled_engine(run: RunConfig) -> bool:
    """Whether the run's agents train on the compiled backend (so a launcher can compile or
    load its kernels once, before it forks them)."""
    if run.algo.engine != "auto" or run.algo.device != "cpu":
        return False
    from fedhpg.common.variants import variants_of

    variants = variants_of(run, [0])
    if _unsupported(run, _policy(run, variants)) is not None:
        return False
    from fedhpg.common.batched.compiled import compiled_unsupported

    return compiled_unsupported(run, variants) is None


def batched_group_or_none(run: RunConfig, variants: Mapping[int, EnvVariant]) -> AgentGroup | None:
    """The compiled backend for these agents, or None where it does not apply."""
    if run.algo.engine != "auto" or run.algo.device != "cpu":
        return None
    policy = _policy(run, variants)  # one env, for the spaces
    if _unsupported(run, policy) is not None:
        return None
    # imported here: numba's import and compilation are paid only by runs that use it
    from fedhpg.common.batched.compiled import CompiledFedHPG, compiled_unsupported

    if compiled_unsupported(run, variants) is None:
        return CompiledFedHPG(run, variants, mlp_shape(policy))
    return None
