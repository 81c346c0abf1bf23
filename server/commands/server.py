"""``fedhpg-server``: the command line of a distributed run's server
(:mod:`fedhpg.server.serving`)."""

from __future__ import annotations

import json
import logging
import socket as socket_module
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zmq

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.runtime.cli import run_entry
from fedhpg.server.checkpoint import (
    interrupted_message,
    nothing_to_run,
    write_atomic,
)
from fedhpg.server.pools import FederationError
from fedhpg.server.run_dir import RunDirectoryError, new_run_dir
from fedhpg.server.serving import bind_error, serve

logger = logging.getLogger(__name__)


def _main(run: RunConfig) -> int:
    out_dir = Path(run.server.out_dir) if run.server.out_dir else new_run_dir(run)
    if run.resume and run.resume.lower() != "true":
        out_dir = Path(run.resume)
    finished = nothing_to_run(out_dir, run.rounds, run.eval.stop_at) if run.resume else None
    if finished is not None:
        sys.stdout.write(finished)
        return 0
    on_bound = None
    if run.server.endpoint_file:
        on_bound = endpoint_writer(run, Path(run.server.endpoint_file))
    try:
        serve(run, out_dir=out_dir, on_bound=on_bound)
    except KeyboardInterrupt:  # SIGINT or SIGTERM (run_entry's handlers): say how to go on
        command = f"fedhpg-server resume=true server.out_dir={out_dir}"
        sys.stderr.write(interrupted_message(out_dir, command) + "\n")
        raise
    except (FederationError, RunDirectoryError) as error:
        logger.error("%s", error)
        return 1
    except zmq.ZMQError as error:
        sys.stderr.write(f"error: {bind_error(run, error)}\n")
        return 1
    return 0


def endpoint_writer(run: RunConfig, path: Path) -> Callable[[str], None]:
    """``server.endpoint_file``: once bound, where agents reach this server, as JSON
    (``host``, ``port``, ``transport``), written atomically so a reader never sees half of it.
    Bound to every interface, the advertised host is ``cluster.advertise_host`` or this node's
    name; otherwise the host it bound."""

    def write(bound: str) -> None:
        record: dict[str, Any] = {"transport": run.server.transport, "endpoint": bound}
        if run.server.transport == "tcp":
            host = run.server.host
            if run.server.bind_all:
                host = run.cluster.advertise_host or socket_module.gethostname()
            record |= {"host": host, "port": int(bound.rsplit(":", 1)[1])}
        try:
            write_atomic(path, json.dumps(record).encode())
        except OSError as error:
            raise RunDirectoryError(
                f"server.endpoint_file: cannot write {path}: {error.strerror or error}"
            ) from None

    return write


def main() -> None:
    sys.exit(run_entry(_main, resumable=True, presets=True))
