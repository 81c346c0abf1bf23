"""Test-wide setup: one torch thread (as in agent processes), test helpers on sys.path, and
how ``make test`` shares the tests between its two pytest-xdist workers.

``make test`` runs ``pytest -n 2 --dist loadscope``; :func:`pytest_xdist_make_scheduler`
makes every test of a module that starts federations (through tests/procs.py, the launcher,
the API's distributed runs, submitit, multiprocessing) one work unit, ``federations``, which
one worker runs in order, as a serial run would: two federations never share the two cores,
and their deadlines keep the margins they were set with. The other modules (in-process
tests, console scripts run to their exit) are spread over both workers a module at a time,
so a module's fixtures are built once. xdist's own ``xdist_group`` mark would say the same,
but with pytest 9 its nodeid suffix no longer takes effect.
"""

from __future__ import annotations

import re
import sys
from functools import cache
from pathlib import Path
from typing import Any

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
torch.set_num_threads(1)

STARTS_FEDERATIONS = re.compile(
    r"^from procs |^import procs\b|fedhpg\.server\.launcher|\bsubmitit\b|\bmultiprocessing\b"
    r"|\bProcess\(|distributed=True",
    re.MULTILINE,
)
"""What a test module that starts federations uses (tests/procs.py: servers, agents, kills;
``api.run(..., distributed=True)`` forks one)."""


@cache
def starts_federations(path: Path) -> bool:
    """Whether the test module at ``path`` starts federations (a module that cannot be read
    fails the run here rather than being spread over both workers)."""
    return bool(STARTS_FEDERATIONS.search(path.read_text(encoding="utf-8")))


@pytest.hookimpl(optionalhook=True)  # a plain pytest without xdist does not know the hook
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    from xdist.scheduler import LoadScopeScheduling

    root = config.rootpath  # nodeids are relative to it

    class FederationsInOrder(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "federations" if starts_federations(root / module) else module

    return FederationsInOrder(config, log)
