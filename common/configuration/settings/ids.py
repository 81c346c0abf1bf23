"""The ids agents and agent hosts go by in logs, records and on the wire."""

from __future__ import annotations


def agent_id_of(index: int, explicit: str | None = None) -> str:
    return explicit if explicit else f"agent-{index}"


def host_id_of(first: int, count: int, explicit: str | None = None) -> str:
    """An agent host's id (its routing identity's prefix, its CURVE key's name)."""
    return explicit if explicit else f"host-{first}-{first + count - 1}"
