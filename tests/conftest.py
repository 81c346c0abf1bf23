"""Test-wide setup: one torch thread (as in agent processes) and test helpers on sys.path."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
torch.set_num_threads(1)
