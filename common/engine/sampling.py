"""Sampling: one episode in every copy of every block, all blocks stepped together.

Block b holds ``counts[b]`` copies of one row's environment (its trajectories this
iteration); every copy's randomness comes from its own trajectory key (its reset from counters
−1, −2, …, its decisions from counters t · noise_size + j, its environment's own draws at step
t, where a family has them, from :data:`ENV_COUNTERS` − t · step_noise − j), so a trajectory
is the same in any company and any layout. Every stepped copy acts in one call of the policy
(``PolicyRows.act`` on a grid of tiles, each of one block's copies under its θ row). Episode
lengths vary a lot and a batch lasts as long as its longest episode, so copies that have
ended leave the stepping: once the running copies are three quarters of those stepped or
fewer, only they are stepped from then on (whole blocks, where the environments step a block
at once: gymnasium's batch environments).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import torch

from fedhpg.common.engine.copies import Copies, columns_of
from fedhpg.common.engine.memory import packed_elements
from fedhpg.common.engine.policy_rows import PolicyRows
from fedhpg.common.engine.trajectories import Trajectories
from fedhpg.common.randomness import uniforms, uniforms64
from fedhpg.envs.device import put_distinct


@dataclass(frozen=True)
class Faults:
    """What attacking rows do to their own sampling (``common/attacks.py``), per block."""

    random_actions: torch.Tensor
    """[B] bool: act uniformly at random over the action space (a faulty actuator)."""
    flipped_rewards: torch.Tensor
    """[B] bool: learn from negated rewards."""


NOISE_CHUNK = 32
"""Time steps of decision draws made at once for every stepped copy."""
ENV_COUNTERS = -(1 << 40)
"""Where the counters of an environment's own draws start (downwards), far below a reset's."""


ACT_TILE = 16
"""Copies per tile of the policy's forward pass while sampling. Every block's copies are cut
into tiles of exactly this many (the last one padded), each tile a row of one policy call with
its block's θ: a matrix product then has one shape whatever the company, and its floats
cannot change with it (a BLAS picks its kernel, and its order of additions, by the shape: on
this project's CPUs a product of fewer than 16 rows rounds differently)."""


def act_tiles_per_call(device: torch.device, num_params: int, agents: int) -> int | None:
    """Tiles one policy call takes while sampling: None on the CPU (one call a step, of any
    size); elsewhere one count for the whole run, every call padded to it, since a GPU library
    may pick its kernel, and so its rounding, by a call's shape. The count is the run's
    ``agents`` (a tile each: a round's first 16 copies of every agent fill its calls), split
    evenly into calls of at most :func:`packed_elements` parameters' worth: a small run does
    not pad to a large call, and a large one is not left with a mostly empty last call."""
    if device.type == "cpu":
        return None
    largest = max(packed_elements(device) // (ACT_TILE * num_params), 1)
    calls = -(-agents // largest)
    return -(-agents // calls)


class _Plan:
    """The copies still stepped (``columns``, increasing, so each block's are adjacent), the
    same as a padded [tiles, ACT_TILE] grid: each stepped block's copies cut into tiles of
    exactly :data:`ACT_TILE` (its last one padded with its first copy), one policy call for
    all of them, or calls of exactly ``tiles_per_call`` tiles (the grid then padded with empty
    tiles to whole calls), and each tile's θ row. A copy's action depends on its own
    observation, draws and θ row alone: which copies share its tile does not change it."""

    def __init__(
        self,
        columns: torch.Tensor,
        owner: torch.Tensor,
        theta: torch.Tensor,
        tiles_per_call: int | None = None,
    ) -> None:
        self.columns = columns
        device = columns.device
        blocks, sizes = torch.unique_consecutive(owner[columns], return_counts=True)
        self.blocks = blocks
        tiles = (sizes + ACT_TILE - 1) // ACT_TILE
        block_of_tile = torch.repeat_interleave(torch.arange(len(blocks), device=device), tiles)
        first_tile = torch.cumsum(tiles, 0) - tiles
        start = (torch.arange(len(block_of_tile), device=device) - first_tile[block_of_tile]) * (
            ACT_TILE
        )
        slots = start.unsqueeze(1) + torch.arange(ACT_TILE, device=device).unsqueeze(0)
        self.valid = slots < sizes[block_of_tile].unsqueeze(1)
        base = (torch.cumsum(sizes, 0) - sizes)[block_of_tile].unsqueeze(1)
        self.grid = columns[torch.where(self.valid, base + slots, base)]
        self.theta = theta[blocks][block_of_tile]
        self.tiles_per_call = tiles_per_call
        if tiles_per_call is not None:  # empty tiles (copy 0, the first block's θ) to whole calls
            extra = -len(block_of_tile) % tiles_per_call
            self.valid = torch.cat([self.valid, self.valid.new_zeros((extra, ACT_TILE))])
            self.grid = torch.cat([self.grid, self.grid.new_zeros((extra, ACT_TILE))])
            self.theta = torch.cat([self.theta, self.theta[:1].expand(extra, -1)])
        self.everyone = len(columns) == len(owner)
        self.slots = None if bool(self.valid.all()) else torch.nonzero(self.valid.flatten())[:, 0]
        """The grid's slots that hold a copy, in order; None when none is padding (the grid's
        actions are then the copies'). Found once per plan: selecting by a mask at every step
        would wait for the device to count it."""

    def act(
        self, policy: PolicyRows, obs: torch.Tensor, noise: torch.Tensor | None
    ) -> torch.Tensor:
        """The grid's actions [tiles, ACT_TILE, ...] from every copy's ``obs`` and decision draws
        ``noise`` [N, k] (None: greedy): one policy call, or calls of ``tiles_per_call`` tiles
        each."""
        per_call = self.tiles_per_call or self.grid.shape[0]
        calls = []
        for start in range(0, self.grid.shape[0], per_call):
            grid = self.grid[start : start + per_call]
            theta = self.theta[start : start + per_call]
            calls.append(policy.act(theta, obs[grid], None if noise is None else noise[grid]))
        return calls[0] if len(calls) == 1 else torch.cat(calls)


def sample(
    policy: PolicyRows,
    copies: Copies,
    theta: torch.Tensor,
    counts: torch.Tensor,
    keys: torch.Tensor,
    horizons: torch.Tensor,
    *,
    greedy: bool = False,
    faults: Faults | None = None,
    action_space: gym.Space | None = None,
    tiles_per_call: int | None = None,
) -> Trajectories:
    """One episode in each copy: block b is row b (θ row ``theta[b]``, ``counts[b]`` ≥ 1
    copies, at most ``horizons[b]`` steps); ``keys`` [N] are the copies' trajectory keys.

    ``tiles_per_call``: None, one policy call per step for every stepped copy (the CPU); else
    calls of exactly so many tiles of :data:`ACT_TILE` copies (a GPU library may pick its
    kernel, and so its rounding, by a call's shape, which must then not depend on the
    company)."""
    device = theta.device
    num_blocks = int(counts.shape[0])
    offsets = copies.offsets
    total = int(offsets[-1])
    owner = torch.repeat_interleave(torch.arange(num_blocks, device=device), counts)
    everyone = torch.arange(num_blocks, device=device)
    obs = copies.reset(everyone, keys)
    horizon = int(horizons.max())
    stop_at = horizons[owner]
    record = _Record(total, obs, device)
    success = torch.zeros(total, dtype=torch.bool, device=device)
    running = torch.ones(total, dtype=torch.bool, device=device)
    flipped = faults.flipped_rewards[owner] if faults is not None else None
    random_columns = faults.random_actions[owner] if faults is not None and not greedy else None
    k = policy.noise_size
    noise: torch.Tensor | None = None  # [N, NOISE_CHUNK, k], from the first chunk's draws
    plan = _Plan(torch.arange(total, device=device), owner, theta, tiles_per_call)
    t = 0
    env_noise = copies.step_noise
    while t < horizon:
        narrowed = _narrowed(plan, running, owner, offsets, copies.any_copies)
        if narrowed is None:
            break
        if isinstance(narrowed, torch.Tensor):
            plan = _Plan(narrowed, owner, theta, tiles_per_call)
        columns = plan.columns
        if not greedy and t % NOISE_CHUNK == 0:
            counters = t * k + torch.arange(NOISE_CHUNK * k, device=device)
            draws = uniforms(keys[columns].unsqueeze(1), counters.unsqueeze(0))
            drawn = draws.reshape(-1, NOISE_CHUNK, k)
            if plan.everyone:
                noise = drawn
            else:  # the first chunk stepped every copy, so the buffer is whole
                assert noise is not None
                put_distinct(noise, columns, drawn)
        acted = plan.act(policy, obs, None if noise is None else noise[:, t % NOISE_CHUNK])
        actions = acted.flatten(0, 1)
        if plan.slots is not None:
            actions = actions.index_select(0, plan.slots)
        if random_columns is not None and bool(random_columns[columns].any()):
            actions = _random_actions(
                actions, random_columns[columns], keys[columns], t, k, action_space
            )
        env_draws = None
        if env_noise:
            counters = ENV_COUNTERS - t * env_noise - torch.arange(env_noise, device=device)
            env_draws = uniforms64(keys[columns].unsqueeze(1), counters.unsqueeze(0))
        step = copies.step(actions, plan.blocks, None if plan.everyone else columns, env_draws)
        live = running if plan.everyone else running[columns]
        reward = step.reward.to(torch.float64) * live
        if flipped is not None:
            reward = torch.where(flipped[columns], -reward, reward)
        record.add(t, None if plan.everyone else columns, obs, actions, reward, running)
        going = live & ~(step.terminated | step.truncated)
        if plan.everyone:  # whole tensors: no indexed write
            success |= live & step.success
            running = going
            obs.copy_(step.obs)
        else:
            put_distinct(success, columns, success[columns] | (live & step.success))
            put_distinct(running, columns, going)
            put_distinct(obs, columns, step.obs.to(obs.dtype))
        t += 1
        running &= stop_at > t
    obs_seen, actions_taken, rewards, alive = record.taken(t)
    return Trajectories(
        obs=obs_seen,
        actions=actions_taken,
        rewards=rewards,
        alive=alive,
        success=success,
        owner=owner,
        counts=counts.clone(),
    )


def _narrowed(
    plan: _Plan,
    running: torch.Tensor,
    owner: torch.Tensor,
    offsets: torch.Tensor,
    any_copies: bool,
) -> torch.Tensor | _Plan | None:
    """The copies the next step steps: ``plan`` itself while it still holds enough running
    copies (or blocks), the running ones once they have shrunk to three quarters of it, None
    when none runs. Copies that step one by one (``any_copies``) are narrowed to the running
    copies; blocks stepped whole (gymnasium's batch environments), to the running blocks."""
    if any_copies:
        live = int(running.sum())  # the step's one wait for the device
        if live == 0:
            return None
        if 4 * live > 3 * len(plan.columns):
            return plan
        return torch.nonzero(running).squeeze(1)
    live_copies = torch.zeros(len(offsets) - 1, dtype=torch.int64, device=running.device)
    block_running = live_copies.index_add_(0, owner, running.long()) > 0
    live = int(block_running.sum())
    if live == 0:
        return None
    if 4 * live > 3 * len(plan.blocks):
        return plan
    return columns_of(offsets, torch.nonzero(block_running).squeeze(1))


class _Record:
    """The steps taken so far, time-major, in buffers that double as episodes grow (a batch
    of short episodes never holds a horizon's worth of memory). Each step's row is written
    whole when the step comes (zeros where no copy was stepped), so the buffers are never
    filled beforehand."""

    START = 64

    def __init__(self, total: int, obs: torch.Tensor, device: torch.device) -> None:
        self.total, self.device = total, device
        self.obs = torch.empty((self.START, *obs.shape), dtype=obs.dtype, device=device)
        self.actions: torch.Tensor | None = None
        self.rewards = torch.empty((self.START, total), dtype=torch.float64, device=device)
        self.alive = torch.empty((self.START, total), dtype=torch.bool, device=device)

    def _grow(self, steps: int) -> None:
        def grown(buffer: torch.Tensor) -> torch.Tensor:
            bigger = buffer.new_empty((steps, *buffer.shape[1:]))
            bigger[: buffer.shape[0]] = buffer
            return bigger

        self.obs, self.rewards, self.alive = grown(self.obs), grown(self.rewards), grown(self.alive)
        if self.actions is not None:
            self.actions = grown(self.actions)

    def add(
        self,
        t: int,
        columns: torch.Tensor | None,
        obs: torch.Tensor,
        actions: torch.Tensor,
        reward: torch.Tensor,
        running: torch.Tensor,
    ) -> None:
        if t >= self.obs.shape[0]:
            self._grow(2 * self.obs.shape[0])
        if self.actions is None:
            self.actions = torch.empty(
                (self.obs.shape[0], self.total, *actions.shape[1:]),
                dtype=actions.dtype,
                device=self.device,
            )
        if columns is None:
            self.obs[t], self.actions[t], self.rewards[t] = obs, actions, reward
        else:
            for row in (self.obs[t], self.actions[t], self.rewards[t]):
                row.zero_()
            put_distinct(self.obs[t], columns, obs[columns])
            put_distinct(self.actions[t], columns, actions)
            put_distinct(self.rewards[t], columns, reward)
        self.alive[t] = running

    def taken(self, steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        assert self.actions is not None, "a batch takes at least one step"
        return self.obs[:steps], self.actions[:steps], self.rewards[:steps], self.alive[:steps]


def _random_actions(
    actions: torch.Tensor,
    chosen: torch.Tensor,
    keys: torch.Tensor,
    step: int,
    k: int,
    space: gym.Space | None,
) -> torch.Tensor:
    """Uniformly random actions for the columns ``chosen`` (from their own decision draws)."""
    u = uniforms(keys.unsqueeze(1), (step * k + torch.arange(k, device=keys.device)).unsqueeze(0))
    if isinstance(space, gym.spaces.Discrete):
        drawn = (u[:, 0] * int(space.n)).long().clamp_max(int(space.n) - 1) + int(space.start)
    elif isinstance(space, gym.spaces.Box) and space.is_bounded():
        low = torch.as_tensor(space.low, dtype=torch.float32, device=keys.device)
        high = torch.as_tensor(space.high, dtype=torch.float32, device=keys.device)
        drawn = low + u[:, : low.numel()].reshape(-1, *low.shape) * (high - low)
    else:
        raise ValueError(f"random actions need a Discrete or bounded Box space, got {space}")
    mask = chosen.reshape(-1, *([1] * (actions.dim() - 1)))
    return torch.where(mask, drawn.to(actions.dtype), actions)
