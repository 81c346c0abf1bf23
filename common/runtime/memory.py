"""Process-level memory settings for agent processes (and in-process pools)."""

from __future__ import annotations

import ctypes
import functools
import gc
import sys

from fedhpg.common.learning.group import SplitGroup

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers
M_MMAP_THRESHOLD = -3


@functools.cache
def pin_malloc_mmap_threshold(size: int = 128 * 1024) -> bool:
    """Fix glibc's mmap threshold at its default 128 KiB (True if it was set).

    glibc raises the threshold each time a large mmapped block is freed, so afterwards the
    rollout buffers and gradient temporaries, whose sizes change with every batch's longest
    episode, come from the heap and fragment it: on LunarLander an agent process grew by
    ~1 GB per minute (17 GB for a 10-agent run); with the threshold pinned it stays at ~0.3 GB.
    Blocks ≥ ``size`` are then always mmapped and returned on free, which costs a few page
    faults per batch. Does nothing outside glibc.
    """
    return _mallopt(M_MMAP_THRESHOLD, size)


@functools.cache
def keep_freed_memory(size: int) -> bool:
    """Keep up to ``size`` bytes of freed memory at the top of the heap instead of returning
    it (True if it was set): with the mmap threshold pinned, glibc no longer adapts its trim
    threshold (128 KiB), so a process that frees a batch's tensors and allocates the next
    one's gives the pages back and faults them in again, every local iteration."""
    return _mallopt(M_TRIM_THRESHOLD, size)


def _mallopt(parameter: int, value: int) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return False
    return bool(mallopt(parameter, value))


ENGINE_MMAP_THRESHOLD = 16 * 2**20
ENGINE_TRIM_THRESHOLD = 64 * 2**20


def tune_malloc_for(group: object) -> None:
    """The engines allocate temporaries of megabytes every local iteration (a batch's steps,
    the estimator's cells, packed tiles and activations; [A, d] rows of θ and the answers
    stacked from them): mmapped and faulted in each time at glibc's 128 KiB threshold, they
    are paid for again every iteration. Their processes take blocks below 16 MiB from the
    heap instead, and keep up to 64 MiB of it when freed, so the next batch reuses them."""
    parts = group.parts if isinstance(group, SplitGroup) else (group,)
    # an attribute, not isinstance: importing the compiled engine would import numba here
    if any(getattr(part, "LARGE_TEMPORARIES", False) for part in parts):
        tune_malloc_for_engine()


def tune_malloc_for_engine() -> None:
    """What :func:`tune_malloc_for` sets for an engine's process: blocks below 16 MiB from
    the heap, up to 64 MiB of it kept when freed (a benchmark of the engine measures it so)."""
    pin_malloc_mmap_threshold(ENGINE_MMAP_THRESHOLD)
    keep_freed_memory(ENGINE_TRIM_THRESHOLD)


def freeze_setup() -> None:
    """Leave what the process holds once its agents are set up (torch, numba's compiled code,
    the config, the group's constants: some 300,000 objects) out of the garbage collector's
    scans. A round creates thousands of short-lived objects, and every so often the collector
    scans the whole heap for cycles: over the setup's objects, a tenth of a second, as long as
    a round of a hundred CartPole agents. What the rounds create is still collected. (No
    collection first: in a hundred one-agent processes on two cores, one each would add
    seconds to the start.)"""
    gc.freeze()
