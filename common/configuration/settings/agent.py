"""The ``agent`` section: one agent process's (or agent host's) own settings."""

from __future__ import annotations

from dataclasses import dataclass

from fedhpg.common.configuration.settings.checks import check_int, require
from fedhpg.common.records.limits import MAX_HOST_AGENTS


@dataclass(kw_only=True)
class AgentConfig:
    """Who this agent process is."""

    index: int = 0
    """Agent index k: selects the environment variant and the compute profile."""
    id: str | None = None
    """Agent id on the wire; None = 'agent-<index>'. For an agent host: the host's id
    (None = 'host-<first>-<last>'); its logical agents are always 'agent-<k>'."""
    first: int | None = None
    """Set: this process is an agent host serving the logical agents first .. first+count-1
    over one connection (``agent.index`` is then unused); None: one agent, ``agent.index``."""
    count: int = 1
    """Agent host: how many consecutive logical agents it serves, from ``agent.first``."""
    connect_timeout_s: float = 60.0
    """Give up if the server has not answered within this time (at start, or after it fell
    silent)."""
    max_restarts: int = 2
    """``fedhpg-run``: restart a crashed agent process up to this many times (it rejoins at
    the current round and redoes the lost work exactly); one more crash stops the run."""


def validate_host_range(agent: AgentConfig, num_agents: int) -> None:
    if agent.first is None:
        return
    check_int(agent.first, "agent.first", low=0)
    check_int(agent.count, "agent.count", low=1)
    require(
        agent.count <= MAX_HOST_AGENTS,
        "agent.count",
        f"got {agent.count}, more than the {MAX_HOST_AGENTS} agents one host may serve",
    )
    require(
        agent.first + agent.count <= num_agents,
        "agent.first",
        f"the range {agent.first}..{agent.first + agent.count - 1} (agent.first, agent.count) "
        f"goes beyond the last agent index {num_agents - 1} (agents.num_agents={num_agents})",
    )
