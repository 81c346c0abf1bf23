"""Where agents run: how many agents one process (an agent host) serves, and the ranges
of agent indices the hosts take.
"""

from __future__ import annotations

import os

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.settings.agents import AUTO
from fedhpg.common.configuration.vocabularies import ROUND_POLICIES
from fedhpg.common.records.limits import MAX_HOST_AGENTS

AUTO_PROCESS_AGENTS = 32
"""``agents.per_host=auto`` gives every agent its own process up to this many agents (or as
many as the machine has cores): the sleeping device emulation, per-agent restarts and
per-agent deadlines stay as written. Beyond it, a process per agent costs more than it
shows (a thousand processes on a few cores register slower than a server waits)."""


def available_cores() -> int:
    """The cores this process may run on (its affinity mask, as a container or SLURM sets it)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):  # not Linux
        return max(os.cpu_count() or 1, 1)


def agents_per_host(run: RunConfig, cores: int | None = None) -> int:
    """The logical agents each agent process serves: ``agents.per_host``, or for 'auto' one
    per process up to :data:`AUTO_PROCESS_AGENTS` agents (or ``cores``, default this
    machine's) and with buffered rounds (which take one agent per process), else one host
    per core."""
    per_host = run.agents.per_host
    if per_host != AUTO:
        return int(per_host)
    cores = available_cores() if cores is None else cores
    num_agents = run.agents.num_agents
    if ROUND_POLICIES.get(run.server.round_policy).asynchronous or num_agents <= max(
        AUTO_PROCESS_AGENTS, cores
    ):
        return 1
    return min(-(-num_agents // cores), MAX_HOST_AGENTS)


def host_ranges(num_agents: int, per_host: int) -> list[tuple[int, int]]:
    """(first, count) of each agent host ``fedhpg-run`` starts with ``agents.per_host``: N
    consecutive indices each, the last one the rest."""
    return [(first, min(per_host, num_agents - first)) for first in range(0, num_agents, per_host)]
