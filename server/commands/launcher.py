"""``fedhpg-run``: one server and K agent processes (or ceil(K/N) agent hosts of N agents,
``agents.per_host``) on this machine, supervised.

torch and the package are imported once here; the server and agents are *forked* from this
process, so K agents start in milliseconds instead of each paying the imports again. Children
die with the launcher (PR_SET_PDEATHSIG); if any child fails, the rest are stopped and the
launcher exits non-zero.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import gc
import logging
import multiprocessing
import os
import signal
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection, wait
from pathlib import Path

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.placement import agents_per_host, available_cores, host_ranges
from fedhpg.common.configuration.settings.agents import AUTO
from fedhpg.common.configuration.settings.ids import host_id_of
from fedhpg.common.learning.engine.devices import check_device_before_fork
from fedhpg.common.runtime.cli import (
    EXIT_RUN_ABORTED,
    EXIT_USAGE,
    HELP_FLAGS,
    PRINTING_FLAGS,
    Interrupted,
    answer_version,
    compose,
    compose_sweep,
    limit_threads,
    repeated_key,
    report_presets,
    setup_logging,
    stop_signals,
    unknown_flag,
)
from fedhpg.common.runtime.composition import (
    algorithm_strategy,
    compose_cfg,
    own_overrides,
    register_schema,
    to_run_config,
)
from fedhpg.common.runtime.help import help_text
from fedhpg.common.runtime.progress import announced_if_slow
from fedhpg.common.runtime.resume import resume_value
from fedhpg.server.run_dir import RunDirectory, RunDirectoryError, new_run_dir

logger = logging.getLogger(__name__)

PR_SET_NAME = 15
PR_SET_PDEATHSIG = 1
STOP_GRACE_S = 3.0
SUPERVISE_S = 1.0
"""The longest the launcher waits between looks at its processes (it wakes at once when one
ends)."""
FINISH_GRACE_S = 10.0
"""After the server completed the run, how long the agent processes may take to end."""
EXIT_INTERRUPTED = 130
BIND_FAILED = b"!"
"""Prefix of the server child's message on the ready pipe when it could not bind."""


def _die_with_parent() -> None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: rely on the launcher's own cleanup
        pass


def _name_process(name: str) -> None:
    """The child's name in ``ps -o comm``, ``top`` and /proc/PID/comm ("agent-2", "server"; the
    kernel keeps 15 bytes), where a forked child would otherwise show the launcher's."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]))
    except (OSError, AttributeError):  # not Linux: the name is only cosmetic
        pass


def _child_setup() -> None:
    _die_with_parent()
    _name_process(multiprocessing.current_process().name)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the launcher decides how to stop
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _server_child(run: RunConfig, out_dir: str, ready: Connection) -> None:
    _child_setup()
    import zmq

    from fedhpg.server.pools import FederationError
    from fedhpg.server.serving import bind_error, serve

    try:
        # Bytes, not Connection.send: that would pickle (harmless here, but no pickle anywhere).
        serve(run, out_dir=Path(out_dir), on_bound=lambda bound: ready.send_bytes(bound.encode()))
    except ConfigError as error:
        sys.stderr.write(f"error: {error}\n")
        sys.exit(2)
    except (FederationError, RunDirectoryError) as error:
        logging.getLogger("fedhpg.server").error("%s", error)
        sys.exit(1)
    except zmq.ZMQError as error:  # the launcher reports it in one line, before any agent starts
        ready.send_bytes(BIND_FAILED + bind_error(run, error).encode())
        sys.exit(1)


def _agent_child(run: RunConfig) -> None:
    _child_setup()
    from fedhpg.agent.main import run_agent

    sys.exit(run_agent(run, forked=True))


def _port_of(endpoint: str) -> int:
    return int(endpoint.rsplit(":", 1)[1])


class Supervisor:
    """Starts, watches, restarts and stops the federation's processes."""

    def __init__(self, *, max_restarts: int = 0) -> None:
        self.context = multiprocessing.get_context("fork")
        self.children: list[multiprocessing.process.BaseProcess] = []
        self.max_restarts = max_restarts
        self._how: dict[str, tuple[Callable[..., None], tuple]] = {}
        self._restarts: dict[str, int] = {}

    def start(
        self, target: Callable[..., None], args: tuple, name: str
    ) -> multiprocessing.process.BaseProcess:
        process = self.context.Process(target=target, args=args, name=name, daemon=False)
        # Everything the launcher holds (torch, the config, the variants' draws) is shared
        # with the forked children; without this their first garbage collection writes to
        # the refcount header of every inherited object and copies its page.
        gc.freeze()
        process.start()
        self.children.append(process)
        self._how[name] = (target, args)
        return process

    def stop_all(self) -> None:
        for child in self.children:
            if child.is_alive():
                child.terminate()
        deadline = time.monotonic() + STOP_GRACE_S
        for child in self.children:
            child.join(max(deadline - time.monotonic(), 0.0))
            if child.is_alive():
                child.kill()
                child.join()

    def _restart(self, child: multiprocessing.process.BaseProcess, code: int) -> bool:
        """Start a crashed agent (or agent host), which exited with ``code``, again if it has
        restarts left."""
        used = self._restarts.get(child.name, 0)
        if child.name == "server" or used >= self.max_restarts:
            return False
        self._restarts[child.name] = used + 1
        logger.warning(
            "%s exited with status %s; restarting it (%d of %d restarts, agent.max_restarts)",
            child.name,
            code,
            used + 1,
            self.max_restarts,
        )
        self.children.remove(child)
        target, args = self._how[child.name]
        self.start(target, args, child.name)
        return True

    def _finish(self) -> int:
        """The server completed the run: give the agent processes FINISH_GRACE_S to end.
        One still running then is stopped with a warning (the run's results are all written;
        a host that missed the server's shutdown, busy reconnecting, would otherwise wait for
        ``agent.connect_timeout_s``); one that ended with an error fails the launch."""
        deadline = time.monotonic() + FINISH_GRACE_S
        for child in self.children:
            child.join(max(deadline - time.monotonic(), 0.0))
        lingering = [c.name for c in self.children if c.exitcode is None]
        failed = [c.name for c in self.children if c.exitcode not in (None, 0)]
        self.stop_all()
        if lingering:
            logger.warning(
                "the run is complete, but %s had not ended %g s after the server; stopped",
                ", ".join(lingering),
                FINISH_GRACE_S,
            )
        if failed:
            logger.error("processes did not finish cleanly: %s", ", ".join(failed))
            return 1
        return 0

    def wait(self, server: multiprocessing.process.BaseProcess) -> int:
        """Until the server ends: 0 if every process ended well, else 1."""
        while True:
            for child in list(self.children):
                # read once: each read polls the process, which may end between two reads
                code = child.exitcode
                if code == EXIT_RUN_ABORTED:
                    continue  # the server ended the run: its own exit status tells how
                if code not in (None, 0) and not self._restart(child, code):
                    logger.error(
                        "%s exited with status %s; stopping the federation", child.name, code
                    )
                    self.stop_all()
                    return 1
            if server.exitcode == 0:
                return self._finish()
            # asleep until a process ends: looking at a hundred agents' exit codes twenty
            # times a second took a tenth of a core from the federation
            wait([c.sentinel for c in self.children if c.exitcode is None], SUPERVISE_S)


def check_launch(run: RunConfig) -> None:
    """What fedhpg-run checks of a composed run before starting anything (no compile, no
    fork): the run as its server will (:func:`~fedhpg.server.assembly.check_run`), a resume's
    run directory and checkpoint as its server will (a refusal is immediate, not after the
    compiled engine's kernels are compiled), every agent's key files, loopback."""
    from fedhpg.common.wire.security import check_launch_keys
    from fedhpg.server.assembly import check_run, resume_checkpoint

    checked = check_run(run, distributed=True)
    if run.resume:
        resume_checkpoint(run, RunDirectory(_resolve_out_dir(run)), checked.strategy)
    if run.server.transport == "tcp" and run.server.bind_all:
        raise ConfigError("server.bind_all", "fedhpg-run runs every process here: keep loopback")
    check_launch_keys(run)  # security: every agent's key, before anything is forked
    check_device_before_fork(run)  # the agents are forked here, onto this machine's devices
    if run.server.out_dir and not run.resume:
        RunDirectory.precheck(Path(run.server.out_dir), resume=False)


def launch(run: RunConfig, out_dir: Path) -> int:
    """Run a whole federation on loopback; returns the process exit status (128 + the
    signal's number when SIGINT or SIGTERM stopped it, after saying how to continue)."""
    supervisor = Supervisor(max_restarts=run.agent.max_restarts)
    try:
        with stop_signals():
            return _launch(run, out_dir, supervisor)
    except Interrupted as interrupted:
        logger.warning("interrupted: stopping the federation")
        supervisor.stop_all()
        _say_how_to_resume(out_dir)
        return interrupted.status
    except KeyboardInterrupt:
        supervisor.stop_all()
        _say_how_to_resume(out_dir)
        return EXIT_INTERRUPTED
    finally:
        supervisor.stop_all()


def _say_how_to_resume(out_dir: Path) -> None:
    from fedhpg.server.checkpoint import interrupted_message

    sys.stderr.write(interrupted_message(out_dir, f"fedhpg-run resume={out_dir}") + "\n")


def _launch(run: RunConfig, out_dir: Path, supervisor: Supervisor) -> int:
    # Before the server is forked: its clock for registrations (server.register_timeout_s)
    # starts when it listens, and a cold numba cache takes tens of seconds to fill.
    prepare_compiled_engine(run)
    receive, send = multiprocessing.Pipe(duplex=False)
    server = supervisor.start(_server_child, (run, str(out_dir), send), "server")
    endpoint = None
    while endpoint is None:
        if receive.poll(0.05):
            message = receive.recv_bytes()
            if message.startswith(BIND_FAILED):
                server.join()
                sys.stderr.write(f"error: {message[len(BIND_FAILED) :].decode()}\n")
                return 1
            endpoint = message.decode()
        elif server.exitcode is not None:
            if server.exitcode == 2:  # a configuration error, already reported in one line
                return 2
            logger.error("the server exited with status %s before listening", server.exitcode)
            return 1
    if run.server.transport == "tcp":
        run = replace(run, server=replace(run.server, port=_port_of(endpoint)))
    agents = agent_processes(run)
    if run.agents.per_host == AUTO and len(agents) < run.agents.num_agents:
        logger.info(
            "agents.per_host=auto: %d agent hosts for %d agents on %d cores%s",
            len(agents),
            run.agents.num_agents,
            available_cores(),
            ""
            if run.agents.virtual_clock
            else "; a host accounts its agents' emulated device time without sleeping "
            "(agents.per_host=1: a sleeping process per agent)",
        )
    _import_agent_program()
    for name, agent_run in agents:
        supervisor.start(_agent_child, (agent_run,), name)
    return supervisor.wait(server)


def _import_agent_program() -> None:
    """Import what every agent child runs, once, before they are forked: they share its
    modules' pages (``gc.freeze`` keeps them shared) where each would otherwise import its own
    copy after the fork, a few MiB a process at one process per agent."""
    import fedhpg.agent.main  # noqa: F401


def prepare_compiled_engine(run: RunConfig) -> None:
    """Compile the compiled engine's kernels here, or load them from numba's cache, when the
    run's agents use it: forked after this, the server and the agents inherit the machine code
    instead of each compiling it (tens of seconds on a machine whose cache is cold), and no
    clock of the run (the server's for registrations) runs while it compiles."""
    from fedhpg.common.learning.batched import uses_compiled_engine

    if not uses_compiled_engine(run):
        return
    from fedhpg.common.learning.batched.backend import warm_up

    with announced_if_slow(
        "compiling the compiled engine's CartPole kernels (numba): the first run after an "
        "install takes ~20 s, later runs load them from numba's cache"
    ):
        seconds = warm_up()
    logger.log(
        logging.INFO if seconds > 5 else logging.DEBUG,
        "compiled engine ready in %.1f s (numba)",
        seconds,
    )


def agent_processes(run: RunConfig) -> list[tuple[str, RunConfig]]:
    """(name, config) of each agent process: one per agent, or with ``agents.per_host`` = N
    above 1 (or what 'auto' makes of it), ceil(K/N) agent hosts of N consecutive indices (the
    last one takes the rest)."""
    k, per_host = run.agents.num_agents, agents_per_host(run)
    if per_host == 1:
        return [
            (f"agent-{i}", replace(run, agent=replace(run.agent, index=i, id=None, first=None)))
            for i in range(k)
        ]
    hosts = []
    for first, count in host_ranges(k, per_host):
        agent = replace(run.agent, index=first, id=None, first=first, count=count)
        hosts.append((host_id_of(first, count), replace(run, agent=agent)))
    return hosts


def _resolve_out_dir(run: RunConfig) -> Path:
    if run.resume and run.resume.lower() != "true":
        return Path(run.resume)
    if run.server.out_dir:
        return Path(run.server.out_dir)
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except ValueError:  # not under Hydra's job machinery (a resume, the API)
        return new_run_dir(run)


def port_named(overrides: list[str]) -> bool:
    """Whether the command line sets ``server.port``: fedhpg-run then listens there; otherwise
    on a free port (the default 5555 is for fedhpg-server and agents started by hand)."""
    return any(o.split("=", 1)[0].lstrip("+") == "server.port" for o in overrides)


def check_endpoint(run: RunConfig) -> None:
    """Probe the address the server will bind, before anything starts. A host this machine
    cannot listen on is a setting: one line, exit 2. A named port that something else holds
    is one line and exit 1: the setting is valid, the machine's state is what fails (as with
    a full disk), and the same command may work a minute later."""
    if run.server.transport != "tcp":
        return
    host, port = run.server.host, run.server.port
    try:
        family, kind, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as libzmq binds
            probe.bind(address)
    except OSError as error:
        reason = error.strerror or str(error)
        if error.errno == errno.EADDRINUSE:
            sys.stderr.write(
                f"error: server.port: cannot listen on {host}:{port}: {reason} (choose another "
                "port, or leave server.port unset for a free one)\n"
            )
            sys.exit(1)
        sys.stderr.write(f"error: server.host: cannot listen on {host}: {reason}\n")
        sys.exit(2)


def run_federation(run: RunConfig, *, port: bool = False) -> int:
    """The federation of ``run``; on the port it names if ``port``, else on a free one."""
    if run.server.transport == "tcp" and not port:
        run = replace(run, server=replace(run.server, port=0))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return launch(run, _resolve_out_dir(run))


_RUN_DIR_EXISTED = True
"""Whether the run directory existed before this command (Hydra makes its job's directory
before the job starts; one it made for a run that fails is removed if the run left it empty).
Unnamed, it is new: :func:`~fedhpg.common.runtime.run_files.hydra_run_dir` never names one
that exists."""


def _hydra_task(cfg: object) -> None:
    from hydra.core.hydra_config import HydraConfig

    setup_logging()  # a sweep job may run in a fresh process (joblib's, submitit's launchers)
    overrides = HydraConfig.get().overrides
    task = list(overrides.task)
    composing = own_overrides([*task, *overrides.hydra])  # with hydra.searchpath
    try:  # checked before Hydra started; again here for what only the job sees
        extra = algorithm_strategy(cfg, composing)
        if extra is not None:  # the algorithm's own strategy (algo=fedpgbr's)
            cfg = compose_cfg([*composing, extra])
        run = to_run_config(cfg)
        check_launch(run)
    except ConfigError as error:
        sys.stderr.write(f"error: {error}\n")
        sys.exit(2)
    limit_threads()
    status = run_federation(run, port=port_named(task))
    if status != 0:
        if not _RUN_DIR_EXISTED:  # Hydra made it for this job: gone if nothing was written
            with contextlib.suppress(OSError):
                _resolve_out_dir(run).rmdir()
        sys.exit(status)


def main() -> None:
    """Every check first (one-line errors, exit 2, nothing created): the run, every point of a
    ``-m`` sweep, or a resume from its run directory's config.json (run here, without Hydra's
    job machinery, so no outputs/ directory appears). Then Hydra runs the job(s)."""
    import hydra

    args = sys.argv[1:]
    answer_version("fedhpg-run", args)
    if any(a in HELP_FLAGS for a in args):
        sys.stdout.write(help_text("fedhpg-run"))
        sys.exit(0)
    flag = unknown_flag(args) or repeated_key(args)  # as typed, before hydra.run.dir is added
    if flag is not None:
        sys.stderr.write(f"error: {flag}\n")
        sys.exit(EXIT_USAGE)
    if not any(a.split("=", 1)[0] in PRINTING_FLAGS for a in args):
        setup_logging()  # --info and the like log through Hydra's own stdout handler
    multirun = any(a in ("-m", "--multirun") for a in args)
    # --cfg, --info, --config-dir ...: Hydra's own (it prints, or reads other configs)
    modes = ("-m", "--multirun", "-r", "--run")
    hydra_flags = any(a.startswith("-") and a not in modes for a in args)
    overrides = own_overrides(args)
    resume = resume_value(overrides) is not None and not multirun
    try:
        if hydra_flags:
            runs: list[RunConfig] = []
        elif multirun:
            runs = compose_sweep(overrides)
        else:
            runs = [compose(overrides, resumable=resume)]
        for run in runs:
            check_launch(run)
    except ConfigError as error:
        sys.stderr.write(f"error: {error}\n")
        sys.exit(EXIT_USAGE)
    port = port_named(overrides)
    for run in runs[:1]:
        check_endpoint(run if port else replace(run, server=replace(run.server, port=0)))
    if runs and not multirun:
        report_presets(overrides)
    if resume:
        from fedhpg.server.checkpoint import nothing_to_run

        run = runs[0]
        finished = nothing_to_run(_resolve_out_dir(run), run.rounds, run.eval.stop_at)
        if finished is not None:  # say so rather than start agents for nothing
            sys.stdout.write(finished)
            sys.exit(0)
        limit_threads()
        sys.exit(run_federation(runs[0], port=port))
    register_schema()
    named = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == "server.out_dir"]
    if named and not any(a.split("=", 1)[0] == "hydra.run.dir" for a in args) and not multirun:
        sys.argv.append(f"hydra.run.dir={named[-1]}")  # Hydra's job directory is the run's
    global _RUN_DIR_EXISTED
    _RUN_DIR_EXISTED = multirun or (bool(named) and Path(named[-1]).exists())
    app = hydra.main(config_path="pkg://fedhpg.conf", config_name="config", version_base=None)(
        _hydra_task
    )
    app()
