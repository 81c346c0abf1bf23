"""``fedhpg-agent``: one agent process of a federation."""

from __future__ import annotations

import logging
import sys

from fedhpg.agent.process import AgentFailure, AgentProcess, RunAborted
from fedhpg.common.config import RunConfig
from fedhpg.common.runtime.cli import EXIT_RUN_ABORTED, run_entry

logger = logging.getLogger(__name__)


def run_agent(run: RunConfig) -> int:
    try:
        AgentProcess(run).run()
    except RunAborted as error:
        logger.error("agent %d: %s", run.agent.index, error)
        return EXIT_RUN_ABORTED
    except AgentFailure as error:
        logger.error("agent %d: %s", run.agent.index, error)
        return 1
    return 0


def main() -> None:
    sys.exit(run_entry(run_agent))
