"""Loaded at interpreter start where this folder is on PYTHONPATH (tests/test_cuda_untouched.py)
and ``FEDHPG_CUDA_TRACE`` names a file: every call of torch's CUDA and accelerator queries, in
this process and every process forked from it, is appended there with its stack. A CPU build
of torch answers them without a GPU, so a test sees on any machine what would initialise
CUDA on a machine with one."""

from __future__ import annotations

import os
import traceback
from collections.abc import Callable
from types import ModuleType
from typing import Any

_LOG = os.environ.get("FEDHPG_CUDA_TRACE")


def _trace(module: ModuleType, name: str, log: str) -> None:
    original: Callable[..., Any] = getattr(module, name)

    def traced(*args: Any, **kwargs: Any) -> Any:
        stack = "".join(traceback.format_stack(limit=10)[:-1])
        with open(log, "a", encoding="utf-8") as out:
            out.write(f"pid {os.getpid()}: {module.__name__}.{name}\n{stack}\n")
        return original(*args, **kwargs)

    setattr(module, name, traced)


if _LOG:
    import torch
    import torch.accelerator
    import torch.cuda

    for _name in ("is_available", "device_count", "_lazy_init", "init", "get_rng_state",
                  "manual_seed", "manual_seed_all", "current_device"):  # fmt: skip
        _trace(torch.cuda, _name, _LOG)
    for _name in ("current_accelerator", "device_count", "is_available"):
        _trace(torch.accelerator, _name, _LOG)
