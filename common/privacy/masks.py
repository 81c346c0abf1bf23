"""The cryptography of secure aggregation, from the ``cryptography`` package.

- Key agreement: X25519 key pairs; two agents derive one 32-byte key from their
  Diffie-Hellman secret with HKDF-SHA256, bound to what it is for (a round's pairwise mask, or
  the channel from one agent to another).
- Masks: a 32-byte seed expanded into uint64 words by AES-256 in counter mode (the keystream of
  zeros), the same words for both agents of a pair.
- Channel: AES-256-GCM under the pair's channel key with a random 96-bit nonce: the shares one
  agent sends another through the server, which can neither read nor alter them unseen.
"""

from __future__ import annotations

import functools
import os
import struct

import numpy as np

try:  # the optional privacy extra; without it a run with privacy= is refused before any use
    from cryptography.exceptions import InvalidTag
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric.x25519 import (
        X25519PrivateKey,
        X25519PublicKey,
    )
    from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
    from cryptography.hazmat.primitives.ciphers.aead import AESGCM
    from cryptography.hazmat.primitives.kdf.hkdf import HKDF
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat
except ImportError:  # pragma: no cover - exercised by tests/test_privacy.py in a subprocess
    pass

KEY_BYTES = 32
NONCE_BYTES = 12
TAG_BYTES = 16


class PeerDataError(ValueError):
    """A peer's value the cryptography cannot use: the peer's fault, never the receiver's."""


class ChannelError(PeerDataError):
    """A ciphertext that does not decrypt under its pair's key (altered, or misaddressed)."""


class BadPublicKey(PeerDataError):
    """A public key that is not 32 bytes, or a low-order point (all zeros among them): no
    secret can be agreed with it."""


def new_private_key() -> bytes:
    """A fresh X25519 private key (raw 32 bytes)."""
    return X25519PrivateKey.generate().private_bytes_raw()


@functools.lru_cache(maxsize=4096)
def _private_key(private: bytes) -> X25519PrivateKey:
    """``private`` loaded once: an agent agrees keys with each of its neighbours, and the
    loading costs as much as the exchange itself."""
    return X25519PrivateKey.from_private_bytes(private)


def public_key(private: bytes) -> bytes:
    """The raw 32-byte public key of ``private``."""
    key = _private_key(private).public_key()
    return key.public_bytes(Encoding.Raw, PublicFormat.Raw)


def agree(private: bytes, peer_public: bytes, purpose: bytes) -> bytes:
    """A 32-byte key that ``private``'s owner and ``peer_public``'s owner both derive:
    HKDF-SHA256 of their X25519 secret, bound to ``purpose``; BadPublicKey for a peer key
    that agrees on nothing."""
    if len(peer_public) != KEY_BYTES:
        raise BadPublicKey(f"a public key is {KEY_BYTES} bytes, got {len(peer_public)}")
    try:
        shared = _private_key(private).exchange(X25519PublicKey.from_public_bytes(peer_public))
    except ValueError:  # a low-order point: the shared secret would be all zeros
        raise BadPublicKey("a public key of low order agrees on no secret") from None
    return HKDF(algorithm=hashes.SHA256(), length=KEY_BYTES, salt=None, info=purpose).derive(shared)


def usable_public_key(key: bytes) -> bool:
    """Whether ``key`` is a public key a secret can be agreed with (32 bytes, not of low
    order: the X25519 exchange with any private key refuses those)."""
    try:
        agree(new_private_key(), key, b"fedhpg secagg key check")
    except BadPublicKey:
        return False
    return True


def mask_purpose(round_index: int, first: int, second: int) -> bytes:
    """What a pairwise mask key is for: the round and the pair (in increasing order)."""
    low, high = sorted((first, second))
    return b"fedhpg secagg mask" + struct.pack("<qqq", round_index, low, high)


def channel_purpose(sender: int, receiver: int) -> bytes:
    """What a channel key is for: one direction between two agents."""
    return b"fedhpg secagg channel" + struct.pack("<qq", sender, receiver)


def expand(seed: bytes, words: int) -> np.ndarray:
    """``words`` pseudorandom uint64 words from a 32-byte ``seed`` (AES-256-CTR keystream)."""
    encryptor = Cipher(algorithms.AES(seed), modes.CTR(bytes(16))).encryptor()
    stream = encryptor.update(bytes(8 * words)) + encryptor.finalize()
    return np.frombuffer(stream, dtype=np.uint64).copy()


def seal(key: bytes, plaintext: bytes, associated: bytes) -> bytes:
    """nonce ‖ AES-GCM(key, nonce, plaintext, associated data)."""
    nonce = os.urandom(NONCE_BYTES)
    return nonce + AESGCM(key).encrypt(nonce, plaintext, associated)


def open_sealed(key: bytes, sealed: bytes, associated: bytes) -> bytes:
    """The plaintext of :func:`seal`'s output; ChannelError if it does not authenticate."""
    if len(sealed) < NONCE_BYTES + TAG_BYTES:
        raise ChannelError("a share's ciphertext is too short")
    try:
        return AESGCM(key).decrypt(sealed[:NONCE_BYTES], sealed[NONCE_BYTES:], associated)
    except (InvalidTag, ValueError):
        raise ChannelError("a share's ciphertext does not authenticate") from None
