"""Whom a key speaks for, by its file's name: ``agent-3`` is agent 3 alone, ``host-0-2`` the
agent host of agents 0..2, any other name its agents after an ``@`` (``alice@5``,
``rack@0-99``). One reading for the CURVE allow-list (:mod:`fedhpg.common.wire.security`) and
the signing roster (:mod:`fedhpg.common.privacy.signing`)."""

from __future__ import annotations

import re
from dataclasses import dataclass

_DEFAULT_AGENT = re.compile(r"agent-(\d+)")
_DEFAULT_HOST = re.compile(r"host-(\d+)-(\d+)")
_AGENTS = re.compile(r"(\d+)(?:-(\d+))?")
BIND = "@"
"""Separates an allow-list entry's name from the agents it speaks for (``alice@5.key``)."""


@dataclass(frozen=True)
class KeyBinding:
    """Who an allowed key speaks for: the id it registers under and exactly these agents."""

    name: str
    agents: range

    def user_id(self) -> str:
        """The ZAP User-Id of a connection made with the key (what the pool reads back)."""
        return f"{self.name}{BIND}{self.agents.start}-{self.agents.stop - 1}"

    @classmethod
    def from_user_id(cls, user_id: str) -> KeyBinding | None:
        name, _, agents = user_id.rpartition(BIND)
        found = _AGENTS.fullmatch(agents)
        if not name or found is None:
            return None
        first = int(found.group(1))
        last = int(found.group(2) or first)
        return cls(name, range(first, last + 1))

    def describe(self) -> str:
        if len(self.agents) == 1:
            return f"{self.name!r} (agent {self.agents.start})"
        return f"{self.name!r} (agents {self.agents.start}..{self.agents.stop - 1})"


def parse_binding(stem: str) -> KeyBinding | str:
    """The binding an allow-list entry's file name (without ``.key``) declares, or why it
    declares none. ``NAME@K`` / ``NAME@F-L`` name the agents outright; ``agent-K`` and
    ``host-F-L`` (the ids ``fedhpg-run`` gives) name them by themselves."""
    name, bind, agents = stem.partition(BIND)
    if bind:
        found = _AGENTS.fullmatch(agents)
        if not name or found is None:
            return f"after {BIND!r} comes an agent index or a range FIRST-LAST, got {agents!r}"
        first, last = int(found.group(1)), int(found.group(2) or found.group(1))
    elif found := _DEFAULT_AGENT.fullmatch(name):
        first = last = int(found.group(1))
    elif found := _DEFAULT_HOST.fullmatch(name):
        first, last = int(found.group(1)), int(found.group(2))
    else:
        return (
            f"names no agents: call it {name}{BIND}<index> (a lone agent) or "
            f"{name}{BIND}<first>-<last> (an agent host); fedhpg-keys --names {name}{BIND}<index> "
            "writes it"
        )
    if last < first:
        return f"the range {first}-{last} is empty"
    return KeyBinding(name, range(first, last + 1))
