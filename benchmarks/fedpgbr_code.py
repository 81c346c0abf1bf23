"""Run FedPG-BR's own code on CartPole-v1 and log, round by round, what it sampled.

FedPG-BR's code (github.com/flint-xf-fan/Byzantine-Federated-RL, ``codes/``) is an external
reference: nothing of it is in this repository. This script runs a checkout of it unchanged
but for one line, and only watches it from outside (it wraps four of its methods). It runs
under that code's own environment (gym 0.24.1, numpy < 2, torch, tqdm, scikit-learn, scipy,
matplotlib, tensorboard), not fedhpg's, and imports nothing of fedhpg.

The one line: FedPG-BR's code never seeds its server's environment (the one its inner loop
samples from and its validation runs in), so a seed does not repeat a run. In a scratch copy,
``codes/run.py``, after ``np.random.seed(run_id)``, add::

    agent.master.env.seed(run_id)

This script refuses a checkout without it. The agents' action draws still depend on which of
its pool's processes takes which agent (each process keeps its own torch generator), so two
runs of one seed may still differ; BENCHMARKS.md says by how much.

Per round it logs (one JSON object a line, after a header line):

- ``counter``: the step counter FedPG-BR's code prints (``Gradient step: …``), which adds
  ``round((K·B_t + b·N_t) / (K + 1))`` a round;
- ``batch_size``: B_t, what each of the K agents sampled;
- ``inner_batches``: how many mini-batches of b trajectories its server sampled;
- ``inner_steps``: how many of them it stepped on (N_t; one fewer than ``inner_batches`` in a
  round whose importance-weight check stopped the loop: its code leaves that batch out of the
  counter);
- ``return``: the greedy validation return it prints after the round (``val_size`` = 10
  episodes);
- ``wall_s``: seconds since the run started (its pool's start-up included).

``benchmarks.thresholds`` turns these into trajectories per agent (its counting convention),
and converts the printed counter where only that is known.

Usage (from the repository root, with that code's Python)::

    /path/to/its/venv/bin/python -m benchmarks.fedpgbr_code --code /path/to/scratch/codes \\
        --seed 0 --server-lr 0.01 --budget 1000 --log run.jsonl > run.out 2> run.err
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from benchmarks.thresholds import sampled_per_agent

SEEDING_LINE = "agent.master.env.seed(run_id)"


class _Stop(Exception):
    """Raised after the round whose trajectories per agent reach the budget."""


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", type=Path, required=True, help="the scratch copy's codes/")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--server-lr", type=float, default=1e-3, help="its opts.lr_model")
    parser.add_argument(
        "--budget", type=float, default=1000.0, help="trajectories per agent to stop at"
    )
    parser.add_argument("--log", type=Path, required=True)
    args = parser.parse_args(argv)
    if SEEDING_LINE not in (args.code / "run.py").read_text():
        sys.exit(
            f"{args.code / 'run.py'} does not seed its server's environment: add "
            f"'{SEEDING_LINE}' after 'np.random.seed(run_id)' (this module's docstring)"
        )
    warnings.filterwarnings("ignore", category=Warning)  # as its own entry point does
    os.environ["KMP_DUPLICATE_LIB_OK"] = "True"
    sys.path.insert(0, str(args.code))  # its modules before any of the same name
    its_agent, its_worker, its_options, its_run = (
        importlib.import_module(name) for name in ("agent", "worker", "options", "run")
    )
    flags = ["--FedPG_BR", "--no_saving", "--no_tb", "--multiple_run", "1"]
    opts = its_options.get_options(["--env_name", "CartPole-v1", "--seed", str(args.seed), *flags])
    opts.lr_model = args.server_lr  # the server's Adam step; its CartPole default is 1e-3
    watch = _Watch(opts.num_worker, opts.b, args.budget, args.log)
    watch.header({"seed": args.seed, "server_lr": args.server_lr, "K": opts.num_worker})
    watch.wrap(its_agent.Agent, its_worker.Worker)
    watch.started = time.perf_counter()
    try:
        its_run.run(opts)
    except _Stop:
        pass
    finally:
        if watch.agent is not None:
            watch.agent.pool.terminate()
        watch.close()


class _Watch:
    """The wrappers around FedPG-BR's Agent and Worker, and the round log they fill."""

    def __init__(self, workers: int, mini_batch: int, budget: float, log: Path) -> None:
        self.workers = workers
        self.mini_batch = mini_batch
        self.budget = budget
        self.file = log.open("w")
        self.agent: Any = None
        self.started = time.perf_counter()
        self.round = 0
        self.per_agent = 0.0
        self.batch_size = 0
        self.inner_batches = 0
        self.inner_steps = 0

    def header(self, fields: dict[str, Any]) -> None:
        self.file.write(json.dumps({"fedpgbr_code": True, "b": self.mini_batch, **fields}) + "\n")

    def close(self) -> None:
        self.file.close()

    def wrap(self, agent_class: Any, worker_class: Any) -> None:
        watch = self
        init, validate = agent_class.__init__, agent_class.start_validating
        collect = worker_class.collect_experience_for_training

        def watched_init(agent: Any, opts: Any) -> None:
            init(agent, opts)
            watch.agent = agent
            agent.pool = _Pool(agent.pool, watch)
            step = agent.optimizer.step

            def watched_step(*args: Any, **kwargs: Any) -> Any:
                watch.inner_steps += 1
                return step(*args, **kwargs)

            agent.optimizer.step = watched_step

        def watched_collect(worker: Any, *args: Any, **kwargs: Any) -> Any:
            if watch.agent is not None and worker is watch.agent.master:
                watch.inner_batches += 1
            return collect(worker, *args, **kwargs)

        def watched_validate(agent: Any, logger: Any, counter: int, *args: Any, **kw: Any) -> Any:
            value = validate(agent, logger, counter, *args, **kw)
            watch.end_round(int(counter), float(value))
            return value

        agent_class.__init__ = watched_init
        agent_class.start_validating = watched_validate
        worker_class.collect_experience_for_training = watched_collect

    def started_round(self, batch_size: int) -> None:
        self.batch_size = batch_size
        self.inner_batches = self.inner_steps = 0

    def end_round(self, counter: int, value: float) -> None:
        self.round += 1
        self.per_agent += sampled_per_agent(
            self.batch_size, self.inner_batches, self.workers, self.mini_batch
        )
        line = {
            "round": self.round,
            "counter": counter,
            "batch_size": self.batch_size,
            "inner_batches": self.inner_batches,
            "inner_steps": self.inner_steps,
            "return": value,
            "wall_s": time.perf_counter() - self.started,
        }
        self.file.write(json.dumps(line) + "\n")
        self.file.flush()
        if self.per_agent >= self.budget:
            raise _Stop


class _Pool:
    """FedPG-BR's worker pool, telling the watch each round's B_t (its starmap's 4th field)."""

    def __init__(self, pool: Any, watch: _Watch) -> None:
        self.pool = pool
        self.watch = watch

    def starmap(self, function: Any, arguments: Any) -> Any:
        rows = list(arguments)
        self.watch.started_round(int(rows[0][3]))
        return self.pool.starmap(function, rows)

    def terminate(self) -> None:
        self.pool.terminate()


if __name__ == "__main__":
    main()
