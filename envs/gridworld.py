"""The paper's GridWorld (Section VI), as a gymnasium env, a batched numpy env, and a family.

Heterogeneity across agents: obstacle layout (rewards), slip probability (dynamics) and
discount factor; optionally the goal cell too. Spaces are identical across variants.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from fedhpg.envs.base import BatchEnv, BatchStep, EnvVariant

EMPTY, START, GOAL, OBSTACLE = ".", "S", "G", "X"
CELL_KINDS = frozenset({EMPTY, START, GOAL, OBSTACLE})
# Action a moves by MOVES[a] = (row delta, column delta): up, down, left, right.
MOVES = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])
ACTION_NAMES = ("up", "down", "left", "right")
GOAL_REWARD, OBSTACLE_REWARD = 1.0, -1.0
DEFAULT_LAYOUT = (
    "S....",
    ".X.X.",
    ".....",
    ".X.X.",
    "....G",
)
ENV_ID = "fedhpg/GridWorld-v0"


@dataclass(frozen=True)
class GridModel:
    """A parsed layout: per-cell tables shared by the single and the batched env."""

    height: int
    width: int
    start: int
    next_state: np.ndarray  # [cells, 4] int64: deterministic move of each action
    reward: np.ndarray  # [cells] float64: reward for entering the cell
    terminal: np.ndarray  # [cells] bool
    goal: np.ndarray  # [cells] bool

    @property
    def num_cells(self) -> int:
        return self.height * self.width


def parse_layout(layout: Sequence[str]) -> GridModel:
    """Check a layout and build its tables; ValueError naming what is wrong."""
    rows = [str(row) for row in layout]
    if not rows or not rows[0]:
        raise ValueError("layout must have at least one non-empty row")
    width = len(rows[0])
    if any(len(row) != width for row in rows):
        raise ValueError(f"layout rows must have equal length, got {[len(r) for r in rows]}")
    cells = "".join(rows)
    unknown = sorted(set(cells) - CELL_KINDS)
    if unknown:
        raise ValueError(f"layout has unknown cell characters {unknown}; allowed: . S G X")
    if cells.count(START) != 1:
        raise ValueError(f"layout needs exactly one start 'S', got {cells.count(START)}")
    if GOAL not in cells:
        raise ValueError("layout needs at least one goal 'G'")
    height = len(rows)
    kinds = np.array(list(cells))
    rows_idx, cols_idx = np.divmod(np.arange(height * width), width)
    next_rows = np.clip(rows_idx[:, None] + MOVES[None, :, 0], 0, height - 1)
    next_cols = np.clip(cols_idx[:, None] + MOVES[None, :, 1], 0, width - 1)
    goal = kinds == GOAL
    obstacle = kinds == OBSTACLE
    return GridModel(
        height=height,
        width=width,
        start=int(cells.index(START)),
        next_state=(next_rows * width + next_cols).astype(np.int64),
        reward=np.where(goal, GOAL_REWARD, np.where(obstacle, OBSTACLE_REWARD, 0.0)),
        terminal=goal | obstacle,
        goal=goal,
    )


def _check_slip(slip: float) -> None:
    if not 0.0 <= slip < 1.0:
        raise ValueError(f"slip must be in [0, 1), got {slip}")


def _check_max_steps(max_steps: int) -> None:
    if int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")


class GridWorldEnv(gym.Env[np.int64, np.int64]):
    """A grid of empty cells, goals and obstacles (the paper's benchmark, Section VI).

    ## Description
    The agent starts on the start cell and must reach a goal while avoiding obstacles. With
    probability ``slip`` the chosen move is replaced by one of the other three, uniformly.

    ## Action Space
    ``Discrete(4)``: 0 up, 1 down, 2 left, 3 right. A move off the grid leaves the agent in place.

    ## Observation Space
    ``Discrete(height × width)``: the index ``row × width + column`` of the agent's cell.

    ## Rewards
    +1 for entering a goal, −1 for entering an obstacle, 0 otherwise.

    ## Starting State
    The cell marked ``S``.

    ## Episode End
    Terminated on entering a goal or an obstacle; truncated after ``max_steps`` steps.
    ``info["is_success"]`` is True when the episode ended in a goal.

    ## Arguments
    ``layout`` (rows of ``. S G X``), ``slip`` in [0, 1), ``max_steps`` ≥ 1,
    ``render_mode`` None or ``"ansi"``.
    """

    metadata = {"render_modes": ["ansi"], "render_fps": 4}  # noqa: RUF012 - gymnasium's convention

    def __init__(
        self,
        *,
        layout: Sequence[str] = DEFAULT_LAYOUT,
        slip: float = 0.0,
        max_steps: int = 50,
        render_mode: str | None = None,
    ) -> None:
        _check_slip(slip)
        _check_max_steps(max_steps)
        if render_mode not in (None, "ansi"):
            raise ValueError(f"render_mode must be None or 'ansi', got {render_mode!r}")
        self.layout = tuple(layout)
        self.model = parse_layout(self.layout)
        self.slip = float(slip)
        self.max_steps = int(max_steps)
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Discrete(self.model.num_cells)
        self.action_space = gym.spaces.Discrete(4)
        self._state = self.model.start
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.int64, dict[str, Any]]:
        super().reset(seed=seed)
        self._state, self._steps = self.model.start, 0
        return np.int64(self._state), {}

    def step(self, action: int) -> tuple[np.int64, float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0..3, got {action!r}")
        direction = int(action)
        if self.slip > 0.0 and self.np_random.random() < self.slip:
            direction = (direction + 1 + int(self.np_random.integers(3))) % 4
        self._state = int(self.model.next_state[self._state, direction])
        self._steps += 1
        terminated = bool(self.model.terminal[self._state])
        truncated = not terminated and self._steps >= self.max_steps
        info = {"is_success": bool(self.model.goal[self._state])}
        return (
            np.int64(self._state),
            float(self.model.reward[self._state]),
            terminated,
            truncated,
            info,
        )

    def render(self) -> str | None:
        if self.render_mode != "ansi":
            return None
        cells = list("".join(self.layout))
        cells[self._state] = "A"
        width = self.model.width
        return "\n".join(
            "".join(cells[r * width : (r + 1) * width]) for r in range(self.model.height)
        )

    def transition_probs(self) -> np.ndarray:
        """P[s, a, s']: the exact dynamics; terminal cells absorb."""
        return transition_probs(self.model, self.slip)

    def reward_table(self) -> np.ndarray:
        """R[s']: reward for entering s'."""
        return self.model.reward.copy()

    def terminal_mask(self) -> np.ndarray:
        return self.model.terminal.copy()


def transition_probs(model: GridModel, slip: float) -> np.ndarray:
    cells = model.num_cells
    probs = np.zeros((cells, 4, cells))
    for action in range(4):
        for direction in range(4):
            weight = 1.0 - slip if direction == action else slip / 3.0
            np.add.at(probs[:, action], (np.arange(cells), model.next_state[:, direction]), weight)
    probs[model.terminal] = 0.0
    for cell in np.flatnonzero(model.terminal):
        probs[cell, :, cell] = 1.0
    return probs


class GridWorldBatchEnv:
    """B copies of one GridWorld, stepped with a few numpy operations per step (no Python loop
    over copies). One uniform per copy and step decides both whether and where it slips."""

    def __init__(
        self, *, layout: Sequence[str], slip: float, max_steps: int, num_envs: int
    ) -> None:
        _check_slip(slip)
        _check_max_steps(max_steps)
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.model = parse_layout(layout)
        self.slip = float(slip)
        self.max_steps = int(max_steps)
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Discrete(self.model.num_cells)
        self.single_action_space = gym.spaces.Discrete(4)
        # Slip lookup: one uniform u picks column j = #{bounds ≤ u}; j < 3 means a slip to
        # direction (a + 1 + j) mod 4, j = 3 means no slip.
        self._slip_bounds = np.array([self.slip / 3, 2 * self.slip / 3, self.slip])
        directions = (np.arange(4)[:, None] + np.array([1, 2, 3, 0])[None, :]) % 4  # [a, j]
        self._outcome = self.model.next_state[:, directions].reshape(-1)  # [(s·4 + a)·4 + j]
        self._not_truncated = np.zeros(num_envs, dtype=bool)
        self._state = np.full(num_envs, self.model.start, dtype=np.int64)
        self._steps = 0
        self._rng = np.random.default_rng(0)

    def reset(self, *, seed: int) -> np.ndarray:
        self._rng = np.random.default_rng(seed)
        self._state = np.full(self.num_envs, self.model.start, dtype=np.int64)
        self._steps = 0
        return self._state.copy()

    def step(self, actions: np.ndarray) -> BatchStep:
        column = np.searchsorted(self._slip_bounds, self._rng.random(self.num_envs), side="right")
        self._state = self._outcome[(self._state * 4 + actions) * 4 + column]
        self._steps += 1
        terminated = self.model.terminal[self._state]
        truncated = ~terminated if self._steps >= self.max_steps else self._not_truncated
        return BatchStep(
            obs=self._state,
            reward=self.model.reward[self._state],
            terminated=terminated,
            truncated=truncated,
            success=self.model.goal[self._state],
        )

    def close(self) -> None:
        pass


@dataclass(frozen=True, kw_only=True)
class GridWorldVariant(EnvVariant):
    """One agent's GridWorld: its own obstacles (and goal), slip and discount."""

    family: str = "gridworld"
    layout: tuple[str, ...] = DEFAULT_LAYOUT
    slip: float = 0.0
    max_steps: int = 50
    params: dict[str, Any] = field(default_factory=dict)

    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        return GridWorldEnv(
            layout=self.layout, slip=self.slip, max_steps=self.max_steps, render_mode=render_mode
        )

    def make_batch_env(self, num_envs: int) -> BatchEnv:
        return GridWorldBatchEnv(
            layout=self.layout, slip=self.slip, max_steps=self.max_steps, num_envs=num_envs
        )

    @property
    def max_episode_steps(self) -> int:
        return self.max_steps


def _monotone_path(
    size: int, rng: np.random.Generator, goal: tuple[int, int]
) -> list[tuple[int, int]]:
    """A random right/down lattice path from (0, 0) to ``goal``."""
    moves = ["down"] * goal[0] + ["right"] * goal[1]
    rng.shuffle(moves)
    cell, path = (0, 0), [(0, 0)]
    for move in moves:
        cell = (cell[0] + 1, cell[1]) if move == "down" else (cell[0], cell[1] + 1)
        path.append(cell)
    return path


def _neighbours(cell: tuple[int, int], size: int) -> list[tuple[int, int]]:
    row, col = cell
    around = [(row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)]
    return [(r, c) for r, c in around if 0 <= r < size and 0 <= c < size]


def _render(size: int, goal: tuple[int, int], obstacles: set[tuple[int, int]]) -> tuple[str, ...]:
    rows = []
    for r in range(size):
        row = []
        for c in range(size):
            if (r, c) == (0, 0):
                row.append(START)
            elif (r, c) == goal:
                row.append(GOAL)
            elif (r, c) in obstacles:
                row.append(OBSTACLE)
            else:
                row.append(EMPTY)
        rows.append("".join(row))
    return tuple(rows)


def make_gridworld_variants(
    *,
    seed: int,
    num_agents: int,
    level: float,
    size: int = 5,
    max_steps: int = 50,
    vary_goal: bool = False,
) -> list[GridWorldVariant]:
    """K GridWorlds from (seed, level): 0 = identical, 1 = most different.

    The start is the top-left cell; the goal is the bottom-right one (or, with ``vary_goal``,
    a per-agent cell of the bottom row / right column: conflicting rewards). A random safe path
    from start to goal is drawn once per run; obstacles are never placed on it nor next to it
    (so a slip off the path does not end the episode), which keeps one common policy able to
    solve every variant. Per agent, with u ~ U(0, 1) drawn from the seed:
    obstacles: a random subset of round(level · #candidates) cells; slip = 0.1 · level · u;
    γ = 0.99 − 0.09 · level · u'.
    """
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"heterogeneity level must be in [0, 1], got {level}")
    if size < 3:
        raise ValueError(f"size must be >= 3, got {size}")
    if num_agents < 1:
        raise ValueError(f"num_agents must be >= 1, got {num_agents}")
    _check_max_steps(max_steps)
    rng = np.random.default_rng([seed, 0x6121D])
    shared_goal = (size - 1, size - 1)
    border = [(size - 1, c) for c in range(1, size)] + [(r, size - 1) for r in range(1, size - 1)]
    variants = []
    shared_path = _monotone_path(size, rng, shared_goal)
    for index in range(num_agents):
        agent_rng = np.random.default_rng([seed, 0x6121D, index])
        goal = border[int(agent_rng.integers(len(border)))] if vary_goal else shared_goal
        path = _monotone_path(size, agent_rng, goal) if vary_goal else shared_path
        protected = set(path)
        for cell in path:
            protected.update(_neighbours(cell, size))
        candidates = [(r, c) for r in range(size) for c in range(size) if (r, c) not in protected]
        if not candidates:  # tiny grids: fall back to cells off the path
            candidates = [
                (r, c) for r in range(size) for c in range(size) if (r, c) not in set(path)
            ]
        count = round(level * len(candidates))
        chosen = agent_rng.choice(len(candidates), size=count, replace=False) if count else []
        obstacles = {candidates[int(i)] for i in chosen}
        slip = round(0.1 * level * float(agent_rng.random()), 4)
        gamma = round(0.99 - 0.09 * level * float(agent_rng.random()), 4)
        variants.append(
            GridWorldVariant(
                index=index,
                gamma=gamma,
                layout=_render(size, goal, obstacles),
                slip=slip,
                max_steps=max_steps,
                params={"slip": slip, "obstacles": len(obstacles), "goal": list(goal)},
            )
        )
    return variants


def shortest_path_policy(layout: Sequence[str], avoid: Sequence[str] = ()) -> np.ndarray:
    """Per cell, the action of a shortest route to a goal that avoids the obstacles of
    ``layout`` and of every layout in ``avoid`` (a common policy for several variants)."""
    model = parse_layout(layout)
    blocked = model.reward < 0
    for other in avoid:
        blocked |= parse_layout(other).reward < 0
    distance = np.full(model.num_cells, np.inf)
    queue = deque(np.flatnonzero(model.goal).tolist())
    distance[model.goal] = 0
    while queue:
        cell = queue.popleft()
        for source in range(model.num_cells):
            reachable = distance[source] == np.inf and not blocked[source]
            if reachable and cell in model.next_state[source]:
                distance[source] = distance[cell] + 1
                queue.append(source)
    best = np.zeros(model.num_cells, dtype=np.int64)
    for cell in range(model.num_cells):
        best[cell] = int(np.argmin(distance[model.next_state[cell]]))
    return best


def register_envs() -> None:
    """Register ``fedhpg/GridWorld-v0`` with gymnasium (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID,
            entry_point="fedhpg.envs.gridworld:GridWorldEnv",
            kwargs={"layout": DEFAULT_LAYOUT, "slip": 0.0, "max_steps": 50},
        )
