"""The compiled CartPole backend (numba): the engine's sampling and score gradients for
agents with the MLP categorical policy on CartPole variants, on the CPU.

:func:`compiled_agents` says which of a group's agents it serves (``algo.engine=auto`` on the
CPU with ``algo.envs=auto``, the MLP categorical policy, a CartPole variant the kernels
model, no attack on sampling);
:func:`fedhpg.common.learning.group.make_agent_group` gives them an engine on this backend and the
others an engine on torch. Any algorithm runs on it: it supplies primitives, not a loop.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from torch import nn

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.attacks import attack_of
from fedhpg.common.learning.batched.mlp import MLPShape
from fedhpg.common.learning.engine.backend import Backend
from fedhpg.common.learning.engine.torch_backend import TorchBackend
from fedhpg.common.learning.policies import AUTO_POLICY, MLP_CATEGORICAL
from fedhpg.envs.base import EnvVariant

if TYPE_CHECKING:
    from fedhpg.common.learning.policies import Policy


def mlp_shape(policy: Policy) -> MLPShape:
    assert isinstance(policy, nn.Module)
    linear = [m for m in policy.modules() if isinstance(m, nn.Linear)]
    return MLPShape((linear[0].in_features, *(m.out_features for m in linear)))


def compiled_backend(
    template: Policy, variants: dict[int, EnvVariant], torch_backend: TorchBackend
) -> Backend:
    """The compiled backend of ``variants`` around the engine's ``torch_backend`` (an
    :class:`~fedhpg.common.learning.engine.engine.Engine`'s ``backend``)."""
    from fedhpg.common.learning.batched.backend import CompiledBackend  # numba's import

    return CompiledBackend(mlp_shape(template), variants, torch_backend)


def compiled_agents(run: RunConfig, variants: Mapping[int, EnvVariant]) -> set[int]:
    """The agents of ``variants`` the compiled backend serves."""
    auto = run.algo.engine == "auto" and run.algo.envs == "auto"
    if not auto or run.algo.device != "cpu" or not variants:
        return set()
    from fedhpg.common.learning.batched.backend import (
        covers,  # numba's import: only where it may run
    )

    served = {
        k
        for k, variant in variants.items()
        if not attack_of(run.attack, k).samples_differently and covers(variant)
    }
    # a CartPole variant's spaces (a Box of observations, Discrete actions) make 'auto' the
    # built-in MLP categorical policy, the one the kernels compute
    return served if run.policy.name in (AUTO_POLICY, MLP_CATEGORICAL) else set()


def uses_compiled_engine(run: RunConfig) -> bool:
    """Whether some of the run's agents train on the compiled backend (so a launcher can
    compile or load its kernels once, before it forks them)."""
    return bool(compiled_agents(run, variants_of(run, [0])))
