"""One side of :mod:`benchmarks.engine_ab`: a group of CartPole agents that trains a round
each time a round number arrives on stdin and answers its seconds and env steps as a JSON
line. Run as a script with whichever ``fedhpg`` is first on the path; it imports only what
every revision of the package has (the config, ``make_agent_group``, ``initial_theta``), from
either layout of ``common/`` (before and after its split by role)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

import fedhpg.common
from fedhpg.common.runtime.cli import compose

# The layout is read from the revision's own folder, not found by trying imports: under an
# editable install a module this revision lacks would be found in the working tree instead.
SPLIT = os.path.isdir(os.path.join(os.path.dirname(fedhpg.common.__file__), "learning"))
"""Whether this revision's common/ is split by role (learning/, records/, ... beneath it)."""
if SPLIT:
    from fedhpg.common.learning.group import make_agent_group
    from fedhpg.common.learning.worker import initial_theta
else:  # earlier revisions: the modules at the top of common/
    from fedhpg.common.group import make_agent_group  # type: ignore[import-not-found,no-redef]
    from fedhpg.common.worker import initial_theta  # type: ignore[import-not-found,no-redef]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--algo", required=True)
    parser.add_argument("--agents", type=int, required=True)
    parser.add_argument("--theta")
    args = parser.parse_args()
    torch.set_num_threads(1)
    run = compose([
        "env=cartpole", f"algo={args.algo}", "agents=population",
        f"agents.num_agents={args.agents}", "agents.clock=counted", "policy.hidden=[16,16]",
        "strategy=mean",
    ])  # fmt: skip
    agents = list(range(args.agents))
    group = make_agent_group(run, agents)
    group.prepare()
    try:  # as an agent host tunes its allocator for its group
        from fedhpg.common.runtime.memory import tune_malloc_for
    except ImportError:
        pass
    else:
        tune_malloc_for(group)
    try:  # and leaves its setup out of the garbage collector's scans, where it does
        from fedhpg.common.runtime.memory import freeze_setup  # type: ignore[attr-defined]
    except ImportError:
        pass
    else:
        freeze_setup()
    theta = torch.load(args.theta) if args.theta else initial_theta(_variant(run), run)
    package = os.path.dirname(os.path.dirname(os.path.abspath(fedhpg.common.__file__)))
    print(json.dumps({"group": type(group).__name__, "package": package}), flush=True)
    for line in sys.stdin:
        index = int(line)
        started = time.perf_counter()
        trained = group.train(index, theta, agents)
        seconds = time.perf_counter() - started
        print(json.dumps({"seconds": seconds, **_measured(trained)}), flush=True)


PHASES = ("engine_sample_s", "engine_gradient_s")
"""The engine's own split of its CPU time, where the revision reports it."""


def _measured(trained):  # type: ignore[no-untyped-def]
    """A round's env steps and phases: from its result's columns, or (older revisions) from
    its per-agent results."""
    if hasattr(trained, "result"):
        stats = trained.result.stats
        phases = {name: sum(v or 0.0 for v in stats.algorithm.get(name, [])) for name in PHASES}
        return {"steps": sum(stats.env_steps), **phases}
    results = trained.values()
    phases = {name: sum(r.stats.algorithm.get(name) or 0.0 for r in results) for name in PHASES}
    return {"steps": sum(r.stats.env_steps for r in results), **phases}


def _variant(run):  # type: ignore[no-untyped-def]
    if SPLIT:
        from fedhpg.common.heterogeneity.variants import variants_of
    else:
        from fedhpg.common.variants import variants_of  # type: ignore[import-not-found,no-redef]

    return variants_of(run, [0])[0]


if __name__ == "__main__":
    main()
