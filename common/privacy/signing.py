"""Authenticated key advertisements for secure aggregation: Ed25519 signatures under keys that
every agent knows from a roster distributed beside the CURVE allow-list, not from the server.

The server relays every public key of a secure round (the agents' long-lived channel keys,
each round's mask keys). Without a check, a server that substitutes its own keys agrees the
masks and opens the shares itself. With a roster (``fedhpg-keys`` writes ``signers/``, one
public signing key per allow-list entry, named the same way: ``agent-3.sign`` speaks for agent
3, ``host-0-99.sign`` for agents 0..99), each agent signs what it advertises, and every agent
checks each key it is handed against the roster entry of the agent it claims to be, before it
uses it. A round with a key that does not verify is refused by the agent that sees it (it
drops out; the server cannot make it use a forged key).

Each round an agent signs its fresh mask key and seed commitment together with its channel
key, its index and the round, so a signature cannot be replayed for another agent, round or
key.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.configuration.key_names import parse_binding
from fedhpg.common.configuration.settings.privacy import SecurityConfig

try:  # the privacy extra (``cryptography``); without it privacy settings are refused at start
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives.asymmetric.ed25519 import (
        Ed25519PrivateKey,
        Ed25519PublicKey,
    )
    from cryptography.hazmat.primitives.serialization import (
        Encoding,
        NoEncryption,
        PrivateFormat,
        PublicFormat,
    )
except ImportError:  # pragma: no cover - the privacy extra is missing
    pass

SIGNATURE_BYTES = 64
SIGNING_KEY_BYTES = 32
SIGNERS_DIR = "signers"
"""The roster's folder in a keys directory: one public signing key per allow-list entry."""
SIGN_SUFFIX = ".sign"
SIGN_SECRET_SUFFIX = ".sign_secret"


class SignatureError(ValueError):
    """A key advertisement that does not verify against the roster."""


def new_signing_key() -> bytes:
    """A fresh Ed25519 private key (raw 32 bytes)."""
    return Ed25519PrivateKey.generate().private_bytes(
        Encoding.Raw, PrivateFormat.Raw, NoEncryption()
    )


def verifying_key(private: bytes) -> bytes:
    """The raw 32-byte public half of ``private``."""
    return (
        Ed25519PrivateKey.from_private_bytes(private)
        .public_key()
        .public_bytes(Encoding.Raw, PublicFormat.Raw)
    )


def mask_statement(
    round_index: int, agent: int, mask_key: bytes, channel_key: bytes, seed_commitment: bytes
) -> bytes:
    """What an agent signs each round: its mask key and seed commitment for the round, and its
    channel key."""
    return (
        b"fedhpg mask key"
        + struct.pack("<qq", round_index, agent)
        + mask_key
        + channel_key
        + seed_commitment
    )


def sign(private: bytes, statement: bytes) -> bytes:
    """The 64-byte Ed25519 signature of ``statement``."""
    return Ed25519PrivateKey.from_private_bytes(private).sign(statement)


@dataclass(frozen=True)
class Roster:
    """Each agent's public signing key, by agent index (from the ``signers/`` folder)."""

    keys: Mapping[int, bytes]

    def check(self, agent: int, statement: bytes, signature: bytes) -> None:
        """SignatureError unless ``signature`` is ``agent``'s roster key's on ``statement``."""
        public = self.keys.get(agent)
        if public is None:
            raise SignatureError(f"agent {agent} has no signing key in the roster")
        if len(signature) != SIGNATURE_BYTES:
            raise SignatureError(f"agent {agent}'s signature is not {SIGNATURE_BYTES} bytes")
        try:
            Ed25519PublicKey.from_public_bytes(public).verify(signature, statement)
        except (InvalidSignature, ValueError):
            raise SignatureError(f"agent {agent}'s key is not signed by its roster key") from None


def write_key_pair(secret_dir: Path, roster_dir: Path, name: str, allowed: str) -> list[Path]:
    """Write ``name``'s signing key pair: the secret as ``<name>.sign_secret`` (mode 0600) in
    ``secret_dir``, the public half as ``<allowed>.sign`` in ``roster_dir``; returns both
    paths (the caller writes into a private staging folder and renames into place)."""
    private = new_signing_key()
    secret = secret_dir / f"{name}{SIGN_SECRET_SUFFIX}"
    public = roster_dir / f"{allowed}{SIGN_SUFFIX}"
    descriptor = os.open(secret, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w", encoding="ascii") as file:
        file.write(private.hex() + "\n")
    public.write_text(verifying_key(private).hex() + "\n", encoding="ascii")
    public.chmod(0o644)
    return [secret, public]


def _read_hex(path: Path) -> bytes:
    try:
        value = bytes.fromhex(path.read_text(encoding="ascii").strip())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise SignatureError(f"cannot read a signing key from {path}: {error}") from None
    if len(value) != SIGNING_KEY_BYTES:
        raise SignatureError(f"{path} does not hold a {SIGNING_KEY_BYTES}-byte signing key")
    return value


def load_signing_key(path: Path) -> bytes:
    """An agent's secret signing key from its ``.sign_secret`` file."""
    return _read_hex(path)


def load_roster(directory: Path) -> Roster:
    """The roster in ``directory``: every ``<entry>.sign`` file, its agents named by the entry
    as an allow-list's are. SignatureError naming the file when one is malformed or two
    entries claim one agent."""
    keys: dict[int, bytes] = {}
    for path in sorted(directory.glob(f"*{SIGN_SUFFIX}")):
        binding = parse_binding(path.name[: -len(SIGN_SUFFIX)])
        if isinstance(binding, str):
            raise SignatureError(f"{path}: {binding}")
        public = _read_hex(path)
        for agent in binding.agents:
            if agent in keys:
                raise SignatureError(f"{path}: agent {agent} already has a signing key")
            keys[agent] = public
    return Roster(keys)


@dataclass(frozen=True)
class AgentSigning:
    """What an agent program signs with and checks against (secure aggregation)."""

    private: bytes
    roster: Roster


def agent_signing(security: SecurityConfig, agent_id: str) -> AgentSigning | None:
    """The signing key of ``agent_id`` (a lone agent's or a host's id) and the roster, from
    ``security.signing_key`` / ``security.signers_dir`` or the keys directory; None where no
    roster is given or found. ConfigError naming the setting when a file is missing or wrong."""
    folder: Path | None = None
    if security.signers_dir is not None:
        folder = Path(security.signers_dir)
        if not folder.is_dir():
            raise ConfigError("security.signers_dir", f"{folder}: no such directory")
    elif security.keys_dir is not None and (Path(security.keys_dir) / SIGNERS_DIR).is_dir():
        folder = Path(security.keys_dir) / SIGNERS_DIR
    if folder is None:
        return None
    if security.signing_key is not None:
        key_path, setting = Path(security.signing_key), "security.signing_key"
    elif security.keys_dir is not None:
        key_path = Path(security.keys_dir) / f"{agent_id}{SIGN_SECRET_SUFFIX}"
        setting = "security.keys_dir"
    else:
        raise ConfigError(
            "security.signing_key", f"a roster is given ({folder}) but no signing key to sign with"
        )
    if not key_path.is_file():
        raise ConfigError(setting, f"{key_path}: no such file (fedhpg-keys writes it)")
    try:
        return AgentSigning(private=load_signing_key(key_path), roster=load_roster(folder))
    except SignatureError as error:
        raise ConfigError(setting, str(error)) from None
