"""A dependency-free progress line: redrawn in place on a terminal, logged otherwise."""

from __future__ import annotations

import logging
import sys
import time
from typing import TextIO

logger = logging.getLogger(__name__)


class Progress:
    """``Progress(total, "rounds")``; call :meth:`update` after each unit of work."""

    def __init__(
        self, total: int, unit: str, *, stream: TextIO | None = None, log_every_s: float = 5.0
    ) -> None:
        self.total = total
        self.unit = unit
        self.done = 0
        self.stream = stream if stream is not None else sys.stderr
        self.interactive = self.stream.isatty()
        self.started = time.monotonic()
        self._last_log = -float("inf")
        self.log_every_s = log_every_s

    def update(self, advance: int = 1, status: str = "") -> None:
        self.done += advance
        elapsed = time.monotonic() - self.started
        rate = self.done / elapsed if elapsed > 0 else 0.0
        remaining = (self.total - self.done) / rate if rate > 0 else float("nan")
        line = f"{self.done}/{self.total} {self.unit} [{elapsed:5.1f}s, eta {remaining:5.1f}s]"
        line = f"{line} {status}"
        if self.interactive:
            width = 24
            filled = int(width * self.done / max(self.total, 1))
            bar = "#" * filled + "-" * (width - filled)
            self.stream.write(f"\r[{bar}] {line}\x1b[K")
            self.stream.flush()
            if self.done >= self.total:
                self.stream.write("\n")
        elif elapsed - self._last_log >= self.log_every_s or self.done >= self.total:
            self._last_log = elapsed
            logger.info("progress %s", line)
