"""Round progress: a live bar on a terminal (rich), plain log lines anywhere else (a file, a
pipe, a CI log), so a redirected log stays readable line by line."""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any, TextIO

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.progress import Progress as RichProgress
from rich.table import Column

logger = logging.getLogger(__name__)


class Progress:
    """``Progress(total, "rounds")``; call :meth:`update` after each unit of work and
    :meth:`close` at the end. The clock starts here: create it when the work starts."""

    def __init__(
        self,
        total: int,
        unit: str,
        *,
        stream: TextIO | None = None,
        log_every_s: float = 5.0,
        done: int = 0,
    ) -> None:
        self.total = total
        self.unit = unit
        self.done = done
        self.stream = stream if stream is not None else sys.stderr
        self.interactive = self.stream.isatty()
        self.started = time.monotonic()
        self._first = done  # a resumed run's rate counts only this process's units
        self._last_log = -float("inf")
        self.log_every_s = log_every_s
        self._bar: Any = None
        if self.interactive:
            self._bar, self._task = _live_bar(self.stream, total, done, unit)

    def update(self, advance: int = 1, status: str = "") -> None:
        self.done += advance
        elapsed = time.monotonic() - self.started
        if self._bar is not None:
            self._bar.update(self._task, advance=advance, status=status, refresh=True)
            if self.done >= self.total:
                self.close()
            return
        rate = (self.done - self._first) / elapsed if elapsed > 0 else 0.0
        remaining = (self.total - self.done) / rate if rate > 0 else float("nan")
        if elapsed - self._last_log >= self.log_every_s or self.done >= self.total:
            self._last_log = elapsed
            logger.info(
                "progress %d/%d %s [%.1fs, eta %.1fs] %s",
                self.done,
                self.total,
                self.unit,
                elapsed,
                remaining,
                status,
            )

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def _live_bar(stream: TextIO, total: int, done: int, unit: str) -> tuple[Any, Any]:
    bar = RichProgress(
        BarColumn(bar_width=20),
        MofNCompleteColumn(),
        TextColumn(unit),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        # the status takes what is left of the line and is cut short, never the counts
        TextColumn(
            "{task.fields[status]}",
            table_column=Column(ratio=1, no_wrap=True, overflow="ellipsis"),
        ),
        console=Console(file=stream),
        expand=True,  # so the status column (ratio=1) gets the rest of the line
    )
    task = bar.add_task(unit, total=total, completed=done, status="")
    bar.start()
    return bar, task


@contextlib.contextmanager
def announced_if_slow(message: str, after_s: float = 1.0) -> Iterator[None]:
    """Log ``message`` (INFO) if the block is still running after ``after_s`` seconds: a
    wait that is usually instant (numba loading its compiled kernels) but sometimes long (the
    first compilation on a machine) is then never silent, and otherwise never mentioned."""
    timer = threading.Timer(after_s, logger.info, args=(message,))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
