"""The batched engine: many agents of one run sampled, evaluated and differentiated together.

:func:`batched_group_or_none` returns an engine for the run when it supports the run's
algorithm, policy and environment family, else None (the caller loops over LocalWorkers).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fedhpg.common.config import RunConfig
from fedhpg.envs.base import EnvVariant

if TYPE_CHECKING:
    from fedhpg.common.group import AgentGroup


def batched_group_or_none(run: RunConfig, variants: dict[int, EnvVariant]) -> AgentGroup | None:
    """The batched engine for these agents, or None where it does not apply (yet)."""
    return None
