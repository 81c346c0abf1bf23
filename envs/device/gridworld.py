"""The paper's GridWorld in torch: each copy on its own variant's grid, slip and step limit.

A copy's state is its cell. One step takes one uniform u from the copy's stream and moves as
:class:`~fedhpg.envs.gridworld.GridWorldBatchEnv` does: with bounds (slip/3, 2·slip/3, slip),
column j = #{bounds ≤ u}; j < 3 slips to direction (a + 1 + j) mod 4, j = 3 keeps the chosen
one (so a slip happens with probability ``slip``, to each other direction with a third of it,
as :class:`~fedhpg.envs.gridworld.GridWorldEnv` draws it). Entering a goal gives +1 and an
obstacle −1, both end the episode; truncated after ``max_steps`` unless terminated. The
grids are tables [layouts, cells, 4 actions, 4 columns] on the device, one per distinct layout
of the variants (``tests/test_device_envs.py`` checks moves, rewards, ends and the slip's
frequencies against the gymnasium environment and its exact transition table).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.device.tensors import Params, TableFamily, TensorCopies
from fedhpg.envs.gridworld import NUM_ACTIONS, GridWorldVariant, parse_layout, slip_bounds


class GridWorldCopies(TensorCopies):
    """GridWorld copies: state [cell] in int64; ``params["table"]`` each copy's layout,
    ``params["bounds"]`` its :func:`~fedhpg.envs.gridworld.slip_bounds`."""

    state_size = 1
    state_dtype = torch.int64
    step_noise = 1
    truncate_terminated = False

    def start(self, uniforms: torch.Tensor, p: Params) -> torch.Tensor:
        return self.tables["start"][p["table"]].unsqueeze(0)

    def advance(
        self, state: torch.Tensor, actions: torch.Tensor, p: Params, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        assert noise is not None, "GridWorld's steps take one uniform per copy"
        column = (noise[:, :1] >= p["bounds"]).sum(1)  # searchsorted(bounds, u, side="right")
        table = p["table"]
        cell = self.tables["outcome"][table, state[0], actions.reshape(-1).long(), column]
        reward = self.tables["reward"][table, cell]
        terminated = self.tables["terminal"][table, cell]
        success = self.tables["goal"][table, cell]
        return cell.unsqueeze(0), reward, terminated, success

    def observe(self, state: torch.Tensor, p: Params) -> torch.Tensor:
        return state[0].clone()


def _layout_tables(layouts: Sequence[tuple[str, ...]]) -> dict[str, torch.Tensor]:
    """Per distinct layout: the start cell, ``outcome[cell, action, column]`` (the move of
    :class:`~fedhpg.envs.gridworld.GridWorldBatchEnv`), the reward for entering each cell,
    whether it ends the episode and whether it is a goal."""
    models = [parse_layout(layout) for layout in layouts]
    columns = np.array([1, 2, 3, 0])
    directions = (np.arange(NUM_ACTIONS)[:, None] + columns[None, :]) % NUM_ACTIONS
    return {
        "start": torch.tensor([m.start for m in models], dtype=torch.int64),
        "outcome": torch.from_numpy(np.stack([m.next_state[:, directions] for m in models])),
        "reward": torch.from_numpy(np.stack([m.reward for m in models])),
        "terminal": torch.from_numpy(np.stack([m.terminal for m in models])),
        "goal": torch.from_numpy(np.stack([m.goal for m in models])),
    }


def gridworld_family(variants: Sequence[EnvVariant], device: torch.device) -> TableFamily | None:
    """The GridWorld variants' grids and slips on ``device`` (None unless every one is a
    GridWorld)."""
    if not all(isinstance(v, GridWorldVariant) for v in variants):
        return None
    grids = [v for v in variants if isinstance(v, GridWorldVariant)]
    if len({(len(v.layout), len(v.layout[0])) for v in grids}) > 1:
        return None  # one observation space per run: never mixed sizes
    distinct: dict[tuple[str, ...], int] = {}
    table = [distinct.setdefault(v.layout, len(distinct)) for v in grids]
    return TableFamily(
        GridWorldCopies,
        {"bounds": [slip_bounds(v.slip) for v in grids], "table": table},
        [v.max_steps for v in grids],
        device,
        dtypes={"bounds": torch.float64, "table": torch.int64},
        tables=_layout_tables(list(distinct)),
    )
