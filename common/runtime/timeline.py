"""Marks of a round's phases across the federation's processes, for ``benchmarks.timeline``.

Off unless ``FEDHPG_TIMELINE=1`` is set when logging is set up (every entry point and forked
child sets it up the same way). Each mark is one DEBUG line of the ``fedhpg.timeline`` logger:
``<wall clock s> <who> <event> <round>``; the wall clock, not a per-process monotonic one, so
that marks of the server and of the hosts can be put on one axis."""

from __future__ import annotations

import logging
import os
import time

logger = logging.getLogger("fedhpg.timeline")
ENV = "FEDHPG_TIMELINE"


def configure() -> None:
    """Turn the marks on in this process if ``FEDHPG_TIMELINE`` asks for them."""
    if os.environ.get(ENV, "") not in ("", "0"):
        logger.setLevel(logging.DEBUG)


def mark(who: str, event: str, round_index: int) -> None:
    if logger.isEnabledFor(logging.DEBUG):
        logger.debug("%.6f %s %s %d", time.time(), who, event, round_index)
