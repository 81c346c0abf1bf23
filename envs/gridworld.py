"""The paper's GridWorld (Section VI), as a gymnasium env, a batched numpy env, and a family.

Heterogeneity across agents: obstacle layout (rewards), slip probability (dynamics) and
discount factor; optionally the goal cell too. Spaces are identical across variants.

The demo set of the default run (``conf/config.yaml``) is :func:`demo_variants`, that is
``make_gridworld_variants(seed=0, num_agents=4, level=0.6)``.
"""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from fedhpg.envs.base import BatchEnv, BatchStep, EnvVariant

logger = logging.getLogger(__name__)

EMPTY, START, GOAL, OBSTACLE = ".", "S", "G", "X"
CELL_KINDS = frozenset({EMPTY, START, GOAL, OBSTACLE})
# Action a moves by MOVES[a] = (row delta, column delta): up, down, left, right.
MOVES = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])
ACTION_NAMES = ("up", "down", "left", "right")
NUM_ACTIONS = 4
GOAL_REWARD, OBSTACLE_REWARD = 1.0, -1.0
DEFAULT_LAYOUT = (
    "S....",
    ".X.X.",
    ".....",
    ".X.X.",
    "....G",
)
ENV_ID = "fedhpg/GridWorld-v0"
_GENERATOR_STREAM = 0x6121D

Cell = tuple[int, int]


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
    if isinstance(layout, str):
        raise ValueError(f"layout must be a sequence of row strings, got the string {layout!r}")
    rows = [str(row) for row in layout]
    if not rows or not rows[0]:
        raise ValueError(f"layout must have at least one non-empty row, got {rows!r}")
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
        raise ValueError(f"layout needs at least one goal 'G', got none in {rows!r}")
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
    if isinstance(max_steps, bool) or int(max_steps) != max_steps or max_steps < 1:
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
    ``layout`` (rows of ``. S G X``: empty, start, goal, obstacle; one ``S``, at least one
    ``G``), ``slip`` in [0, 1), ``max_steps`` ≥ 1, ``render_mode`` None or ``"ansi"``.
    The exact model is available as :meth:`transition_probs`, :meth:`reward_table` and
    :meth:`terminal_mask`, for dynamic programming.
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
        self.model = parse_layout(layout)
        self.layout = tuple(layout)
        self.slip = float(slip)
        self.max_steps = int(max_steps)
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Discrete(self.model.num_cells)
        self.action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self._state = self.model.start
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.int64, dict[str, Any]]:
        super().reset(seed=seed)
        self._state, self._steps = self.model.start, 0
        return np.int64(self._state), {}

    def step(self, action: int | np.int64) -> tuple[np.int64, float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0..3, got {action!r}")
        direction = int(action)
        if self.slip > 0.0 and self.np_random.random() < self.slip:
            direction = (direction + 1 + int(self.np_random.integers(3))) % NUM_ACTIONS
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
        """P[s, a, s'] in float64: the exact dynamics, with terminal cells absorbing so that
        value iteration needs no special case for them."""
        return _transition_table(self.model, self.slip)

    def reward_table(self) -> np.ndarray:
        """R[s']: the reward for entering s' (rewards depend only on the cell entered)."""
        return self.model.reward.copy()

    def terminal_mask(self) -> np.ndarray:
        """bool[s]: cells whose entry ends the episode (goals and obstacles)."""
        return self.model.terminal.copy()


def _transition_table(model: GridModel, slip: float) -> np.ndarray:
    cells = np.arange(model.num_cells)
    probs = np.zeros((model.num_cells, NUM_ACTIONS, model.num_cells))
    for action in range(NUM_ACTIONS):
        for direction in range(NUM_ACTIONS):
            weight = 1.0 - slip if direction == action else slip / 3.0
            np.add.at(probs[:, action], (cells, model.next_state[:, direction]), weight)
    terminal = np.flatnonzero(model.terminal)
    probs[terminal] = 0.0
    probs[terminal, :, terminal] = 1.0
    return probs


def slip_bounds(slip: float) -> list[float]:
    """(slip/3, 2·slip/3, slip): a step's uniform u picks column j = #{bounds ≤ u}."""
    return [slip / 3, 2 * slip / 3, slip]


class GridWorldBatchEnv:
    """B copies of one GridWorld, stepped with a few numpy operations per step (no Python loop
    over copies), because the sampler spends most of its time here.

    One uniform u per copy and step decides both whether and where it slips: column
    j = #{bounds ≤ u} of ``bounds = (slip/3, 2·slip/3, slip)``; j < 3 slips to direction
    (a + 1 + j) mod 4, j = 3 keeps the chosen direction. ``outcome[s, a, j]`` is precomputed.
    Each step returns fresh arrays; ``obs`` is also the batch's state, so callers must not
    write into it (copying it would cost more than the rest of the step's bookkeeping).
    """

    def __init__(
        self, *, layout: Sequence[str], slip: float, max_steps: int, num_envs: int
    ) -> None:
        _check_slip(slip)
        _check_max_steps(max_steps)
        if isinstance(num_envs, bool) or int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs}")
        self.model = parse_layout(layout)
        self.slip = float(slip)
        self.max_steps = int(max_steps)
        self.num_envs = int(num_envs)
        self.single_observation_space = gym.spaces.Discrete(self.model.num_cells)
        self.single_action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self._slip_bounds = np.array(slip_bounds(self.slip))
        columns = np.array([1, 2, 3, 0])
        directions = (np.arange(NUM_ACTIONS)[:, None] + columns[None, :]) % NUM_ACTIONS
        self._outcome = self.model.next_state[:, directions]  # [s, a, j]
        self._state = np.full(self.num_envs, self.model.start, dtype=np.int64)
        self._steps = 0
        self._rng = np.random.default_rng(0)

    def reset(self, *, seed: int) -> np.ndarray:
        self._rng = np.random.default_rng(seed)
        self._state = np.full(self.num_envs, self.model.start, dtype=np.int64)
        self._steps = 0
        return self._state.copy()

    def step(self, actions: np.ndarray) -> BatchStep:
        """Copies that already ended keep moving; the sampler masks them (see BatchEnv).

        Actions are checked (cheaply) because numpy would silently read a negative action as
        another one, and an action of 4 as the next cell's action 0.
        """
        actions = np.asarray(actions)
        if (
            actions.shape != self._state.shape
            or actions.dtype.kind not in "iu"
            or np.count_nonzero(actions >> 2)
        ):
            raise ValueError(self._bad_actions(actions))
        column = np.searchsorted(self._slip_bounds, self._rng.random(self.num_envs), side="right")
        state = self._outcome[self._state, actions, column]
        self._state = state
        self._steps += 1
        terminated = self.model.terminal[state]
        if self._steps >= self.max_steps:
            truncated = ~terminated
        else:
            truncated = np.zeros(self.num_envs, dtype=bool)
        return BatchStep(
            obs=state,
            reward=self.model.reward[state],
            terminated=terminated,
            truncated=truncated,
            success=self.model.goal[state],
        )

    def _bad_actions(self, actions: np.ndarray) -> str:
        values = np.unique(actions).tolist() if actions.size <= 1000 else "..."
        return (
            f"actions must be {self.num_envs} integers in 0..3, got shape {actions.shape}, "
            f"dtype {actions.dtype} and values {values}"
        )

    def close(self) -> None:
        pass


@dataclass(frozen=True, kw_only=True)
class GridWorldVariant(EnvVariant):
    """One agent's GridWorld: its own obstacles (and goal), slip and discount.

    ``safe_path`` lists the cells (indices ``row × width + column``) from start to goal that
    the generator kept free of obstacles and of obstacle neighbours; empty for hand-made
    variants. It is not in ``params`` because ``params`` is what runs report per agent.
    """

    has_goal: ClassVar[bool] = True
    family: str = "gridworld"
    layout: tuple[str, ...] = DEFAULT_LAYOUT
    slip: float = 0.0
    max_steps: int = 50
    safe_path: tuple[int, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "layout", tuple(self.layout))
        object.__setattr__(self, "safe_path", tuple(int(cell) for cell in self.safe_path))
        parse_layout(self.layout)
        _check_slip(self.slip)
        _check_max_steps(self.max_steps)
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")

    def make_env(self, *, render_mode: str | None = None) -> GridWorldEnv:
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


def _monotone_path(rng: np.random.Generator, goal: Cell) -> list[Cell]:
    """A random right/down lattice path from (0, 0) to ``goal``."""
    moves = ["down"] * goal[0] + ["right"] * goal[1]
    rng.shuffle(moves)
    cell, path = (0, 0), [(0, 0)]
    for move in moves:
        cell = (cell[0] + 1, cell[1]) if move == "down" else (cell[0], cell[1] + 1)
        path.append(cell)
    return path


def _neighbours(cell: Cell, size: int) -> list[Cell]:
    row, col = cell
    around = [(row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)]
    return [(r, c) for r, c in around if 0 <= r < size and 0 <= c < size]


def _obstacle_candidates(path: Sequence[Cell], size: int) -> list[Cell]:
    """Cells neither on the path nor 4-adjacent to it (a slip off the path stays safe); only
    off the path when that leaves no room (grids too small for a margin)."""
    on_path = set(path)
    protected = set(on_path)
    for cell in path:
        protected.update(_neighbours(cell, size))
    grid = [(r, c) for r in range(size) for c in range(size)]
    candidates = [cell for cell in grid if cell not in protected]
    return candidates or [cell for cell in grid if cell not in on_path]


def _obstacle_count(level: float, num_candidates: int) -> int:
    """Grows with ``level`` but stops at half the candidates: layouts differ most when each
    agent blocks about half of them, whereas blocking all would make every agent's layout the
    same again."""
    return min(round(level * num_candidates), (num_candidates + 1) // 2)


def _goal_cells(size: int) -> list[Cell]:
    """Goals for ``vary_goal``: the bottom row and right column, at least ``size`` steps from
    the start."""
    bottom = [(size - 1, c) for c in range(1, size)]
    right = [(r, size - 1) for r in range(1, size - 1)]
    return bottom + right


def _render(size: int, goal: Cell, obstacles: set[Cell]) -> tuple[str, ...]:
    def kind(cell: Cell) -> str:
        if cell == (0, 0):
            return START
        if cell == goal:
            return GOAL
        return OBSTACLE if cell in obstacles else EMPTY

    return tuple("".join(kind((r, c)) for c in range(size)) for r in range(size))


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

    The start is the top-left cell and the goal the bottom-right one. A random monotone safe
    path from start to goal is drawn once per seed; obstacles are never placed on it nor next
    to it (a slip off the path does not end the episode), so that one common policy, following
    the path, solves every variant. Per agent, with u, u' ~ U(0, 1) drawn from (seed, agent):
    obstacles are a random subset of the candidate cells of size :func:`_obstacle_count`;
    slip = 0.1 · level · u; γ = 0.99 − 0.09 · level · u'.

    With ``vary_goal`` every agent gets its own goal on the bottom row or right column
    (distinct while there are enough such cells) and its own safe path: rewards that conflict,
    so no common policy need solve all variants. The goals differ even at level 0.

    Agent k's variant depends on (seed, k) alone, not on K: :func:`gridworld_variants_at`
    makes the variants of some agents only.
    """
    return gridworld_variants_at(
        range(num_agents),
        seed=seed,
        num_agents=num_agents,
        level=level,
        size=size,
        max_steps=max_steps,
        vary_goal=vary_goal,
    )


@functools.lru_cache(maxsize=8)
def _shared_draws(seed: int, size: int) -> tuple[tuple[Cell, ...], tuple[int, ...]]:
    """What every agent of a seed shares: the safe path to the common goal, and the order in
    which ``vary_goal`` hands out the border goals (both from the seed's stream, in this order)."""
    rng = np.random.default_rng([seed, _GENERATOR_STREAM])
    shared_path = _monotone_path(rng, (size - 1, size - 1))
    order = rng.permutation(len(_goal_cells(size)))
    return tuple(shared_path), tuple(int(i) for i in order)


def gridworld_variants_at(
    indices: Sequence[int],
    *,
    seed: int,
    num_agents: int,
    level: float,
    size: int = 5,
    max_steps: int = 50,
    vary_goal: bool = False,
) -> list[GridWorldVariant]:
    """The variants of agents ``indices`` of :func:`make_gridworld_variants`, each built alone."""
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"heterogeneity level must be in [0, 1], got {level}")
    if size < 3:
        raise ValueError(f"size must be >= 3, got {size}")
    if num_agents < 1:
        raise ValueError(f"num_agents must be >= 1, got {num_agents}")
    _check_max_steps(max_steps)
    shared_goal = (size - 1, size - 1)
    shared_path, order = _shared_draws(seed, size)
    border = _goal_cells(size)
    shared_candidates = _obstacle_candidates(shared_path, size)
    variants = []
    for index in map(int, indices):
        goal = border[order[index % len(border)]] if vary_goal else shared_goal
        agent_rng = np.random.default_rng([seed, _GENERATOR_STREAM, index])
        path = _monotone_path(agent_rng, goal) if vary_goal else list(shared_path)
        candidates = _obstacle_candidates(path, size) if vary_goal else shared_candidates
        count = _obstacle_count(level, len(candidates))
        chosen: list[int] = (
            agent_rng.choice(len(candidates), size=count, replace=False).tolist() if count else []
        )
        obstacles = {candidates[int(i)] for i in chosen}
        slip = round(0.1 * level * float(agent_rng.random()), 4)
        gamma = round(0.99 - 0.09 * level * float(agent_rng.random()), 4)
        variant = GridWorldVariant(
            index=index,
            gamma=gamma,
            layout=_render(size, goal, obstacles),
            slip=slip,
            max_steps=max_steps,
            safe_path=tuple(r * size + c for r, c in path),
            params={"slip": slip, "obstacles": len(obstacles), "goal": list(goal)},
        )
        logger.debug("gridworld variant %d: %s slip=%g γ=%g", index, variant.layout, slip, gamma)
        variants.append(variant)
    return variants


def demo_variants() -> list[GridWorldVariant]:
    """The four agents of the default run (``conf/config.yaml``: seed 0, level 0.6)."""
    return make_gridworld_variants(seed=0, num_agents=4, level=0.6)


def shortest_path_policy(
    layout: Sequence[str], avoid: Sequence[Sequence[str]] = (), path: Sequence[int] = ()
) -> np.ndarray:
    """One deterministic action per cell, common to several variants: along ``path`` (cell
    indices ending at a goal) follow it; elsewhere take a shortest route to a goal of
    ``layout`` that avoids the obstacles of ``layout`` and of every layout in ``avoid``."""
    model = parse_layout(layout)
    blocked = model.reward < 0
    for other in avoid:
        blocked |= parse_layout(other).reward < 0
    distance = np.where(model.goal, 0.0, np.inf)
    for _ in range(model.num_cells):
        relaxed = np.where(
            model.goal | blocked, distance, distance[model.next_state].min(axis=1) + 1
        )
        if np.array_equal(relaxed, distance):
            break
        distance = relaxed
    policy = np.argmin(distance[model.next_state], axis=1).astype(np.int64)
    for here, there in itertools.pairwise(path):
        moves = np.flatnonzero(model.next_state[here] == there)
        if moves.size == 0:
            raise ValueError(f"path must move between adjacent cells, got {here} -> {there}")
        policy[here] = moves[0]
    return policy


def success_probability(env: GridWorldEnv, policy: np.ndarray | None = None) -> float:
    """P(enter a goal within ``env.max_steps`` steps from the start), exactly, by finite-horizon
    dynamic programming on the env's tables: under a deterministic ``policy`` (one action per
    cell), or under the best policy for this env alone when ``policy`` is None."""
    probs = env.transition_probs()
    goal = env.reward_table() > 0
    alive = ~env.terminal_mask()
    into_goal = probs @ goal.astype(np.float64)  # [s, a]
    staying = probs * alive  # [s, a, s']: transitions that keep the episode going
    cells = np.arange(probs.shape[0])
    value = np.zeros(probs.shape[0])
    for _ in range(env.max_steps):
        q = into_goal + staying @ value
        value = q.max(axis=1) if policy is None else q[cells, policy]
    return float(value[env.model.start])


def register_envs() -> None:
    """Register ``fedhpg/GridWorld-v0`` with gymnasium; idempotent, since both the package
    import and users may call it."""
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID,
            entry_point="fedhpg.envs.gridworld:GridWorldEnv",
            kwargs={"layout": DEFAULT_LAYOUT, "slip": 0.0, "max_steps": 50},
        )
