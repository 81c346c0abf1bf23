"""Torch writes that both the environments on a device and the engine make.

A leaf module (it imports torch alone), so the engine (``fedhpg.common``) and the torch
environments (``fedhpg.envs.device``, which import nothing of the federation) share one
implementation.
"""

from __future__ import annotations

import torch


def put_distinct(
    target: torch.Tensor,
    index: torch.Tensor | tuple[torch.Tensor | slice, ...],
    values: torch.Tensor | float,
) -> None:
    """``target[index] = values`` where ``index`` names no position twice.

    Such a write has one result whatever order a device makes it in. Torch's deterministic
    algorithms (the engine runs under them off the CPU) cannot know the positions are
    distinct and sort the indices of every indexed write on a GPU first; this makes the write
    without that sort (deterministic mode stays on for everything else)."""
    if target.device.type == "cpu" or not torch.are_deterministic_algorithms_enabled():
        target[index] = values
        return
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(False)
    try:
        target[index] = values
    finally:
        torch.use_deterministic_algorithms(True, warn_only=warn_only)
