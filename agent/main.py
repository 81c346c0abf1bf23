"""``fedhpg-agent``: one agent process of a federation, or an agent host (``agent.first``)."""

from __future__ import annotations

import logging
import sys

from fedhpg.agent.host import AgentHost
from fedhpg.agent.process import AgentFailure, AgentProcess, RunAborted
from fedhpg.common.config import RunConfig
from fedhpg.common.runtime.cli import EXIT_RUN_ABORTED, run_entry

logger = logging.getLogger(__name__)


def run_agent(run: RunConfig) -> int:
    host = run.agent.first is not None
    who = (
        f"host {run.agent.first}..{run.agent.first + run.agent.count - 1}"
        if run.agent.first is not None
        else f"agent {run.agent.index}"
    )
    try:
        (AgentHost(run) if host else AgentProcess(run)).run()
    except RunAborted as error:
        logger.error("%s: %s", who, error)
        return EXIT_RUN_ABORTED
    except AgentFailure as error:
        logger.error("%s: %s", who, error)
        return 1
    return 0


def main() -> None:
    sys.exit(run_entry(run_agent))
