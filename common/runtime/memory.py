"""Process-level memory settings for agent processes (and in-process pools)."""

from __future__ import annotations

import ctypes
import functools
import sys

M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number


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
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, size))


ENGINE_MMAP_THRESHOLD = 16 * 2**20


def tune_malloc_for(group: object) -> None:
    """The engines allocate temporaries of megabytes every round (trajectory buffers, packed
    tiles and activations every local iteration; [A, d] rows of θ and the answers stacked from
    them): mmapped and faulted in each time at glibc's 128 KiB threshold, they are paid for
    again every round. Their processes take blocks below 16 MiB from the heap instead, where
    they are reused."""
    from fedhpg.common.group import SplitGroup

    parts = group.parts if isinstance(group, SplitGroup) else (group,)
    # an attribute, not isinstance: importing the compiled engine would import numba here
    if any(getattr(part, "LARGE_TEMPORARIES", False) for part in parts):
        pin_malloc_mmap_threshold(ENGINE_MMAP_THRESHOLD)
