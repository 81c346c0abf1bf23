"""``fedhpg-agent``: one agent of a federation (``agent.index``), or an agent host serving
``agent.count`` agents from ``agent.first``: the same program (:mod:`fedhpg.agent.host`)."""

from __future__ import annotations

import logging
import sys

from fedhpg.agent.host import AgentFailure, AgentHost, RunAborted
from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.runtime.cli import EXIT_RUN_ABORTED, run_entry

logger = logging.getLogger(__name__)


def run_agent(run: RunConfig, *, forked: bool = False) -> int:
    """Serve the agents of ``run`` until the server ends the run; the exit status. Why it
    cannot go on is one ``error:`` line on stderr (exit 1, or 3 when the server aborted the
    run); ``forked`` by fedhpg-run, a log line instead, and none for an aborted run, which
    the server reports once for every agent."""
    first = run.agent.first
    who = (
        f"host {first}..{first + run.agent.count - 1}"
        if first is not None
        else f"agent {run.agent.index}"
    )
    try:
        AgentHost(run).run()
    except RunAborted as error:
        if forked:
            logger.debug("%s: %s", who, error)
        else:
            sys.stderr.write(f"error: {who}: {error}\n")
        return EXIT_RUN_ABORTED
    except AgentFailure as error:
        if forked:
            logger.error("%s: %s", who, error)
        else:
            sys.stderr.write(f"error: {who}: {error}\n")
        return 1
    return 0


def main() -> None:
    sys.exit(run_entry(run_agent))
