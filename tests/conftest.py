"""Test-wide setup: one torch thread (as in agent processes), test helpers on sys.path, and
how ``make test`` shares the tests between its two pytest-xdist workers.

``make test`` runs ``pytest -n 2 --dist loadscope``; :func:`pytest_xdist_make_scheduler`
makes every test that starts federations (tests/federation_tests.py reads which: tests/procs.py's
servers and agents, the launcher, the API's distributed runs, submitit, multiprocessing) one
work unit, ``federations``, which one worker starts first and runs in order, as a serial run
would: no two of them share the two cores, and their deadlines keep the margins they were
set with. The other tests (in-process tests, also those in a module that starts federations
elsewhere) are spread over both workers a module at a time, so a module's fixtures are built
once per worker that runs it. A test marked ``alongside`` (the long tier's docs pages, make
test's fedhpg-run runs of plugins and a sweep: federations on free ports that wait with the
defaults' wide margins, checked by their outputs alone) is spread one case a work unit, beside
the federations: ``make test-long`` runs the pages on both workers. xdist's own ``xdist_group``
mark would say the same, but with pytest 9 its nodeid suffix no longer takes effect.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
torch.set_num_threads(1)


@pytest.hookimpl(optionalhook=True)  # a plain pytest without xdist does not know the hook
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    from federation_tests import runs_alongside, starts_federations  # tests/ is on sys.path
    from xdist.scheduler import LoadScopeScheduling

    root = config.rootpath  # nodeids are relative to it

    class FederationsInOrder(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            if runs_alongside(root / module, nodeid):
                return nodeid
            return "federations" if starts_federations(root / module, nodeid) else module

        def _assign_work_unit(self, node: Any) -> None:
            if "federations" in self.workqueue:  # the longest serial chain starts first
                self.workqueue.move_to_end("federations", last=False)
            super()._assign_work_unit(node)

    return FederationsInOrder(config, log)
