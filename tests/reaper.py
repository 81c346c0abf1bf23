"""Run a command as a child subreaper and report every process it leaves behind.

``python reaper.py CMD ...``: processes that CMD started and that outlive it (its jobs, their
children) are re-parented to this process instead of init, so they can be seen. Once CMD has
exited, any still alive after GRACE_S is named on stderr (``left behind: PID CMDLINE``) and
killed, and the exit status is LEFT_BEHIND; otherwise CMD's own status."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import time

PR_SET_CHILD_SUBREAPER = 36
GRACE_S = 1.0
LEFT_BEHIND = 99


def _reap() -> None:
    with contextlib.suppress(ChildProcessError):
        while os.waitpid(-1, os.WNOHANG)[0] != 0:
            pass


def _children() -> list[int]:
    with open(f"/proc/{os.getpid()}/task/{os.getpid()}/children") as handle:
        return [int(p) for p in handle.read().split()]


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as handle:
            return handle.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except FileNotFoundError:
        return "?"


def main() -> int:
    if ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1) != 0:
        sys.stderr.write("reaper: cannot become a child subreaper\n")
        return 2
    status = subprocess.call(sys.argv[1:])
    deadline = time.monotonic() + GRACE_S
    while True:
        _reap()
        left = _children()
        if not left or time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    for pid in left:
        sys.stderr.write(f"left behind: {pid} {_cmdline(pid)}\n")
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    _reap()
    return LEFT_BEHIND if left else status


if __name__ == "__main__":
    sys.exit(main())
