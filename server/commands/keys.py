"""``fedhpg-keys``: CURVE key pairs for a server and its agents, and the server's allow-list.

Writes, into one directory::

    server.key, server.key_secret        the server's key pair
    agent-<k>.key, agent-<k>.key_secret  each agent's key pair (or the names given)
    allowed/agent-<k>.key                the agents' public keys: the server's allow-list
    agent-<k>.sign_secret                each agent's signing key (secure aggregation)
    signers/agent-<k>.sign               the agents' public signing keys: every agent's roster

An allow-list entry binds its key to the agents it may speak for
(:func:`~fedhpg.common.configuration.key_names.parse_binding`): ``agent-<k>`` and ``host-<f>-<l>``
by their names, any other name by a suffix (``--names alice@3`` writes ``alice.key_secret`` and
``allowed/alice@3.key``; ``--names rack@0-99`` a host's key for agents 0..99).

The signing keys authenticate what agents advertise in a secure round
(:mod:`fedhpg.common.privacy.signing`): the roster goes to every agent host, so that no server
can substitute a key. Secret files are mode 0600 from the start (generated in a private
temporary directory, then renamed into place). Existing keys are never replaced without ``--force``.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import stat
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import zmq
import zmq.auth

from fedhpg.common.configuration.key_names import BIND, parse_binding
from fedhpg.common.configuration.placement import host_ranges
from fedhpg.common.configuration.settings.ids import host_id_of
from fedhpg.common.privacy.signing import (
    SIGN_SECRET_SUFFIX,
    SIGN_SUFFIX,
    SIGNERS_DIR,
    write_key_pair,
)
from fedhpg.common.runtime.cli import version_text
from fedhpg.common.wire.security import (
    ALLOWED_DIR,
    PUBLIC_SUFFIX,
    SECRET_SUFFIX,
    SERVER_KEY_NAME,
)

EXIT_USAGE = 2
MAX_AGENTS = 10_000
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


@dataclass(frozen=True)
class Entry:
    """One agent's (or host's) key pair: its own files' name and its allow-list entry's."""

    name: str
    allowed: str
    """The allow-list file's name without ``.key`` (``name``, or ``name@agents``)."""


WHERE_TO = """\
Which file goes where:
  server host:   {dir}/server.key_secret and the directory {dir}/allowed/
                 fedhpg-server security.curve=true security.keys_dir={dir} ...
  agent host k:  {dir}/agent-k.key_secret, {dir}/server.key, and for secure aggregation
                 {dir}/agent-k.sign_secret and the directory {dir}/signers/ (nothing else)
                 fedhpg-agent agent.index=k security.curve=true security.keys_dir=<their dir> ...
  (a host of agents f..l: {dir}/host-f-l.key_secret, .sign_secret, server.key, signers/)
  one machine:   fedhpg-run security.curve=true security.keys_dir={dir}
Never copy a .key_secret or .sign_secret file anywhere but to the host it belongs to.
"""


class UsageError(Exception):
    """Bad input: reported as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise UsageError(message)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="fedhpg-keys",
        description=(
            "Generate CURVE key pairs for a fedhpg server and its agents, and the allow-list "
            "of agent public keys the server reads (security.keys_dir)."
        ),
        epilog=WHERE_TO.format(dir="DIR"),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "-V", "--version", action="version", version=version_text(parser.prog).strip()
    )
    parser.add_argument("directory", metavar="DIR", help="where to write the keys (created)")
    who = parser.add_mutually_exclusive_group()
    who.add_argument(
        "-k",
        "--agents",
        metavar="K",
        default="4",
        help="number of agents: key pairs agent-0 ... agent-(K-1) (default 4)",
    )
    who.add_argument(
        "--names",
        nargs="+",
        metavar="NAME",
        help=(
            "ids to generate keys for, instead of agent-0 ...: agent-K and host-F-L speak for "
            f"the agents they name; any other id says which, NAME{BIND}K (a lone agent with "
            f"agent.id=NAME agent.index=K) or NAME{BIND}F-L (an agent host)"
        ),
    )
    parser.add_argument(
        "--per-host",
        metavar="N",
        default=None,
        help="with --agents K: keys for agent hosts of N agents each (host-0-<N-1>, ...), as "
        "fedhpg-run agents.per_host=N starts them",
    )
    parser.add_argument(
        "--force", action="store_true", help="replace keys that already exist in DIR"
    )
    return parser


def _integer(flag: str, value: str, high: int) -> int:
    try:
        number = int(value)
    except ValueError:
        raise UsageError(f"{flag}: got {value!r}, must be an integer >= 1") from None
    if not 1 <= number <= high:
        raise UsageError(f"{flag}: got {number}, must be an integer in 1..{high}")
    return number


def _entries(agents: str, names: list[str] | None, per_host: str | None) -> list[Entry]:
    if names is not None:
        if per_host is not None:
            raise UsageError("--per-host: goes with --agents, not with --names")
        entries = []
        for given in names:
            name = given.partition(BIND)[0]
            if not NAME.fullmatch(name):
                raise UsageError(
                    f"--names: {name!r} is not a valid agent id (letters, digits, '.', '_', '-'; "
                    "up to 64 characters, starting with a letter or digit)"
                )
            if name == SERVER_KEY_NAME:
                raise UsageError(f"--names: {name!r} is the server's key name")
            binding = parse_binding(given)
            if isinstance(binding, str):
                raise UsageError(f"--names: {given!r} {binding}")
            entries.append(Entry(name, given))
        seen = [e.name for e in entries]
        duplicates = sorted({n for n in seen if seen.count(n) > 1})
        if duplicates:
            raise UsageError(f"--names: given more than once: {', '.join(duplicates)}")
        return entries
    count = _integer("--agents", agents, MAX_AGENTS)
    if per_host is None:
        return [Entry(f"agent-{k}", f"agent-{k}") for k in range(count)]
    size = _integer("--per-host", per_host, count)
    return [Entry(n, n) for n in (host_id_of(f, c) for f, c in host_ranges(count, size))]


def _targets(directory: Path, entries: list[Entry]) -> list[Path]:
    paths = [directory / f"{SERVER_KEY_NAME}{suffix}" for suffix in (PUBLIC_SUFFIX, SECRET_SUFFIX)]
    for entry in entries:
        paths += [
            directory / f"{entry.name}{PUBLIC_SUFFIX}",
            directory / f"{entry.name}{SECRET_SUFFIX}",
        ]
        paths.append(directory / ALLOWED_DIR / f"{entry.allowed}{PUBLIC_SUFFIX}")
        paths.append(directory / f"{entry.name}{SIGN_SECRET_SUFFIX}")
        paths.append(directory / SIGNERS_DIR / f"{entry.allowed}{SIGN_SUFFIX}")
    return paths


def _prepare(directory: Path) -> None:
    folders = (directory, directory / ALLOWED_DIR, directory / SIGNERS_DIR)
    for folder in folders:
        if folder.exists() and not folder.is_dir():
            raise UsageError(f"{folder}: exists and is not a directory")
    try:
        for folder in folders[1:]:
            folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"cannot create {directory}: {error.strerror or error}") from None
    if not all(os.access(folder, os.W_OK | os.X_OK) for folder in folders):
        raise UsageError(f"cannot write to {directory}: permission denied")


def generate(directory: Path, entries: list[Entry], *, force: bool = False) -> list[Path]:
    """Write the server's and the agents' key pairs and the allow-list; returns the files."""
    targets = _targets(directory, entries)
    if not force:
        existing = [path for path in targets if path.exists() or path.is_symlink()]
        if existing:
            more = f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""
            raise UsageError(f"{existing[0]} already exists{more}; use --force to replace keys")
    _prepare(directory)
    try:
        # mkdtemp is mode 0700: no secret is readable by others, not even for an instant.
        staging = Path(tempfile.mkdtemp(prefix=".fedhpg-keys-", dir=directory))
    except OSError as error:
        raise UsageError(f"cannot write to {directory}: {error.strerror or error}") from None
    try:
        written: list[Path] = []
        for entry in [Entry(SERVER_KEY_NAME, ""), *entries]:
            public, secret = (Path(p) for p in zmq.auth.create_certificates(staging, entry.name))
            os.chmod(secret, stat.S_IRUSR | stat.S_IWUSR)
            os.chmod(public, 0o644)
            if entry.allowed:
                allowed = staging / f"{entry.name}.allowed"
                shutil.copyfile(public, allowed)
                os.chmod(allowed, 0o644)
                target = directory / ALLOWED_DIR / f"{entry.allowed}{PUBLIC_SUFFIX}"
                os.replace(allowed, target)
                written.append(target)
                secret_signing, public_signing = write_key_pair(
                    staging, staging, entry.name, entry.allowed
                )
                for path, folder in (
                    (secret_signing, directory),
                    (public_signing, directory / SIGNERS_DIR),
                ):
                    os.replace(path, folder / path.name)
                    written.append(folder / path.name)
            for path in (public, secret):
                os.replace(path, directory / path.name)
                written.append(directory / path.name)
        return written
    except OSError as error:
        raise UsageError(f"cannot write to {directory}: {error.strerror or error}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _stale_allowed(directory: Path, entries: list[Entry]) -> list[str]:
    """Allow-list entries this run did not write: they stay valid until removed."""
    current = {f"{entry.allowed}{PUBLIC_SUFFIX}" for entry in entries}
    return sorted(
        path.name[: -len(PUBLIC_SUFFIX)]
        for path in (directory / ALLOWED_DIR).glob(f"*{PUBLIC_SUFFIX}")
        if path.name not in current
    )


def run(argv: Sequence[str]) -> int:
    try:
        args = _parser().parse_args(list(argv))
        entries = _entries(args.agents, args.names, args.per_host)
        directory = Path(args.directory)
        generate(directory, entries, force=args.force)
    except UsageError as error:
        sys.stderr.write(f"fedhpg-keys: error: {error}\n")
        return EXIT_USAGE
    names = [e.allowed for e in entries]
    shown = ", ".join(names) if len(names) <= 6 else f"{names[0]} ... {names[-1]}"
    sys.stdout.write(
        f"wrote CURVE keys to {directory}: server and {len(names)} agents ({shown}); "
        f"allow-list {directory / ALLOWED_DIR}\n" + WHERE_TO.format(dir=directory)
    )
    stale = _stale_allowed(directory, entries)
    if stale:
        sys.stdout.write(
            f"note: {directory / ALLOWED_DIR} still allows {', '.join(stale)} from before; "
            f"delete their {PUBLIC_SUFFIX} files there to revoke them\n"
        )
    return 0


def main() -> None:
    sys.exit(run(sys.argv[1:]))
