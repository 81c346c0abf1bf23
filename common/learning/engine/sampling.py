"""Sampling: one episode in every copy of every block, all blocks stepped together.

Block b holds ``counts[b]`` copies of one row's environment (its trajectories this
iteration); every copy's randomness comes from its own trajectory key (its reset from counters
−1, −2, …, its decisions from counters t · noise_size + j, its environment's own draws at step
t, where a family has them, from :data:`ENV_COUNTERS` − t · step_noise − j), so a trajectory
is the same in any company and any layout.

Every step is the same function of the batch's shapes alone: every copy acts, in one call of
the policy on a grid of tiles built once per call (:class:`_Grid`, each tile one block's
copies under its θ row), every copy is stepped (the torch families; gymnasium's batch
environments skip the blocks whose copies have all ended), and a copy whose episode has ended
is masked out (``running``), never recorded as alive. Nothing inside a step waits for the
device: whether any copy still runs is asked every :data:`END_CHECK` steps, and the batch's
length (its longest episode) is read once at the end. A step holds no data-dependent shape, no
index found on the host and no allocation (the record buffers grow at those checks only), so
a GPU runs it without waiting, and it could be captured as one graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from fedhpg.common.learning.engine.copies import Copies
from fedhpg.common.learning.engine.memory import (
    ENV_CHUNK,
    NOISE_CHUNK,
    RECORD_START,
    packed_elements,
)
from fedhpg.common.learning.engine.policy_rows import PolicyRows
from fedhpg.common.learning.engine.trajectories import Trajectories
from fedhpg.common.learning.randomness import uniforms, uniforms64


@dataclass(frozen=True)
class Faults:
    """What attacking rows do to their own sampling (``common/learning/attacks.py``), per block."""

    random_actions: torch.Tensor
    """[B] bool: act uniformly at random over the action space (a faulty actuator)."""
    flipped_rewards: torch.Tensor
    """[B] bool: learn from negated rewards."""


ENV_COUNTERS = -(1 << 40)
"""Where the counters of an environment's own draws start (downwards), far below a reset's."""
END_CHECK = 16
"""Steps between two checks whether any copy still runs (the sampler's only waits for the
device while it steps). A batch steps at most ``END_CHECK − 1`` steps past its longest
episode, whose results are masked and cut off; :data:`RECORD_START` is a multiple of it, so
the record buffers grow at checks only."""


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


class _Grid:
    """Every copy as a padded [tiles, ACT_TILE] grid, built once per batch: each block's
    copies cut into tiles of exactly :data:`ACT_TILE` (its last one padded with its first
    copy), one policy call for all of them, or calls of exactly ``tiles_per_call`` tiles (the
    grid then padded with empty tiles, copy 0 under the first block's θ, to whole calls), and
    each call's θ rows, split into the policy's parameters once. A copy's action depends on
    its own observation, draws and θ row alone: which copies share its tile does not change
    it."""

    def __init__(
        self,
        policy: PolicyRows,
        counts: list[int],
        theta: torch.Tensor,
        tiles_per_call: int | None,
    ) -> None:
        device = theta.device
        sizes = np.asarray(counts, dtype=np.int64)
        tiles = (sizes + ACT_TILE - 1) // ACT_TILE
        block_of_tile = np.repeat(np.arange(len(sizes)), tiles)
        first_tile = np.cumsum(tiles) - tiles
        start = (np.arange(len(block_of_tile)) - first_tile[block_of_tile]) * ACT_TILE
        slots = start[:, None] + np.arange(ACT_TILE)[None, :]
        valid = slots < sizes[block_of_tile][:, None]
        base = (np.cumsum(sizes) - sizes)[block_of_tile][:, None]
        grid = np.where(valid, base + slots, base)
        extra = 0 if tiles_per_call is None else -len(block_of_tile) % tiles_per_call
        if extra:  # empty tiles (copy 0, the first block's θ) to whole calls
            valid = np.concatenate([valid, np.zeros((extra, ACT_TILE), dtype=bool)])
            grid = np.concatenate([grid, np.zeros((extra, ACT_TILE), dtype=np.int64)])
            block_of_tile = np.concatenate([block_of_tile, np.zeros(extra, dtype=np.int64)])
        self.policy = policy
        self.tiles = len(block_of_tile)
        per_call = tiles_per_call or max(self.tiles, 1)
        self.calls = [slice(at, at + per_call) for at in range(0, self.tiles, per_call)]
        """The tiles of each policy call."""
        rows = theta[torch.from_numpy(block_of_tile).to(device)]
        self.theta = [rows[call] for call in self.calls]
        """Each call's tiles' θ rows."""
        self.params = [policy.params(part) for part in self.theta] if policy.batched else None
        """The same as the policy's parameters (a policy whose maths broadcast over rows);
        None: each call goes through :meth:`PolicyRows.act`."""
        padded = not bool(valid.all())
        self.index = torch.from_numpy(grid).to(device) if padded else None
        """The copy in each slot; None when the grid is every copy in order (a view)."""
        self.slots = torch.from_numpy(np.flatnonzero(valid)).to(device) if padded else None
        """The slots that hold a copy, in order (None: every slot)."""

    def draws(self, noise: torch.Tensor) -> torch.Tensor:
        """Decision draws [..., N, k] of every copy as the grid's [..., tiles, ACT_TILE, k]."""
        if self.index is None:
            return noise.unflatten(-2, (self.tiles, ACT_TILE))
        return noise[..., self.index, :]

    def _call(self, i: int, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        if self.params is None:
            return self.policy.act(self.theta[i], obs, noise)
        return self.policy.policy.act_with(self.params[i], obs, noise)

    def act(self, obs: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """Every copy's action [N, ...] from every copy's ``obs`` and the grid's decision
        draws ``noise`` [tiles, ACT_TILE, k] (:meth:`draws`; None: greedy): one policy call,
        or calls of ``tiles_per_call`` tiles each."""
        if self.index is None:
            grid_obs = obs.view(self.tiles, ACT_TILE, *obs.shape[1:])
        else:
            grid_obs = obs[self.index]
        if len(self.calls) == 1:
            acted = self._call(0, grid_obs, noise)
        else:
            acted = torch.cat([
                self._call(i, grid_obs[call], None if noise is None else noise[call])
                for i, call in enumerate(self.calls)
            ])  # fmt: skip
        acted = acted.flatten(0, 1)
        return acted if self.slots is None else acted.index_select(0, self.slots)


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
    end_check: int = END_CHECK,
) -> Trajectories:
    """One episode in each copy: block b is row b (θ row ``theta[b]``, ``counts[b]`` ≥ 1
    copies, at most ``horizons[b]`` steps); ``keys`` [N] are the copies' trajectory keys.

    ``tiles_per_call``: None, one policy call per step for every copy (the CPU); else calls
    of exactly so many tiles of :data:`ACT_TILE` copies (a GPU library may pick its kernel,
    and so its rounding, by a call's shape, which must then not depend on the company).
    ``end_check``: steps between two checks whether any copy still runs (a divisor of
    :data:`RECORD_START`)."""
    assert RECORD_START % end_check == 0, "the record grows at checks only"
    device = theta.device
    sizes = counts.tolist()
    num_blocks, total = len(sizes), sum(sizes)
    owner = torch.repeat_interleave(torch.arange(num_blocks, device=device), counts)
    grid = _Grid(policy, sizes, theta, tiles_per_call)
    obs = copies.reset(keys)
    horizon = int(horizons.max())
    # each copy's horizon, where the rows' differ (else the loop's bound is every row's)
    stop_at = horizons[owner] if bool((horizons < horizon).any()) else None
    record = _Record(total, obs, device)
    success = torch.zeros(total, dtype=torch.bool, device=device)
    running = torch.ones(total, dtype=torch.bool, device=device)
    lengths = torch.zeros(total, dtype=torch.int64, device=device)
    flipped = None
    if faults is not None and bool(faults.flipped_rewards.any()):
        flipped = faults.flipped_rewards[owner]
    randomised = None
    if faults is not None and not greedy and bool(faults.random_actions.any()):
        randomised = _RandomActions(faults.random_actions[owner], action_space, device)
    k = policy.noise_size
    keyed = keys.unsqueeze(1)
    draws_at = torch.arange(NOISE_CHUNK * k, device=device).unsqueeze(0)
    env_noise = copies.step_noise
    env_at = ENV_COUNTERS - torch.arange(ENV_CHUNK * env_noise, device=device).unsqueeze(0)
    noise: tuple[torch.Tensor, ...] = ()  # the chunk's decision draws, a grid per step
    copy_noise: tuple[torch.Tensor, ...] = ()  # the same, [N, k] per step (attackers' draws)
    env_draws: tuple[torch.Tensor, ...] = ()  # the chunk's environment draws, [N, s] per step
    t = 0
    with torch.no_grad():
        while t < horizon:
            if t % end_check == 0:
                if t and not bool(running.any()):  # the step's only wait, every end_check
                    break
                record.reserve(t + end_check)
            if t % NOISE_CHUNK == 0 and not greedy:
                drawn = uniforms(keyed, draws_at + t * k).view(total, NOISE_CHUNK, k)
                noise = grid.draws(drawn.transpose(0, 1)).unbind(0)
                if randomised is not None:
                    copy_noise = drawn.unbind(1)
            if env_noise and t % ENV_CHUNK == 0:
                # step t + s, draw j: counter ENV_COUNTERS − (t + s)·s_n − j
                env_chunk = uniforms64(keyed, env_at - t * env_noise)
                env_draws = env_chunk.view(total, ENV_CHUNK, env_noise).unbind(1)
            at = t % NOISE_CHUNK
            actions = grid.act(obs, noise[at] if noise else None)
            if randomised is not None:
                actions = randomised(actions, copy_noise[at])
            step = copies.step(actions, running, env_draws[t % ENV_CHUNK] if env_draws else None)
            record.add(t, obs, actions, step.reward)
            lengths += running
            success |= running & step.success
            running.masked_fill_(step.terminated | step.truncated, False)
            t += 1
            if stop_at is not None:
                running &= stop_at > t
            obs = step.obs
    steps = int(lengths.max())  # the batch's longest episode: its length
    alive = torch.arange(steps, device=device).unsqueeze(1) < lengths
    obs_seen, actions_taken, rewards = record.taken(steps)
    rewards.masked_fill_(~alive, 0.0)  # the record's own buffer: zeroed where nothing ran
    if flipped is not None:
        rewards.mul_(torch.where(flipped, -1.0, 1.0).to(rewards.dtype))
    return Trajectories(
        obs=obs_seen,
        actions=actions_taken,
        rewards=rewards,
        alive=alive,
        success=success,
        owner=owner,
        counts=counts.clone(),
        lengths=lengths,
    )


class _Record:
    """The steps taken so far, time-major, in buffers that double as episodes grow (a batch
    of short episodes never holds a horizon's worth of memory), at the end checks only. Each
    step's row is written whole, a stepped copy's raw results whether it runs or not (the
    rewards of the steps that did not happen are zeroed at the end), so the buffers are never
    filled beforehand. Every step's rows are views made when the buffers are (a step writes
    into its views: no indexing)."""

    def __init__(self, total: int, obs: torch.Tensor, device: torch.device) -> None:
        self.total, self.device = total, device
        self.obs = torch.empty((RECORD_START, *obs.shape), dtype=obs.dtype, device=device)
        self.actions: torch.Tensor | None = None
        self.rewards = torch.empty((RECORD_START, total), dtype=torch.float64, device=device)
        self.rows: list[tuple[torch.Tensor, ...]] = []
        """Each buffer's rows (obs, rewards, then actions once their type is known)."""

    def reserve(self, steps: int) -> None:
        """Room for ``steps`` steps (doubling)."""
        size = self.obs.shape[0]
        while size < steps:
            size *= 2
        if size != self.obs.shape[0]:

            def grown(buffer: torch.Tensor) -> torch.Tensor:
                bigger = buffer.new_empty((size, *buffer.shape[1:]))
                bigger[: buffer.shape[0]] = buffer
                return bigger

            self.obs, self.rewards = grown(self.obs), grown(self.rewards)
            if self.actions is not None:
                self.actions = grown(self.actions)
            self.rows = []
        if not self.rows:
            self.rows = [self.obs.unbind(0), self.rewards.unbind(0)]
            if self.actions is not None:
                self.rows.append(self.actions.unbind(0))

    def add(self, t: int, obs: torch.Tensor, actions: torch.Tensor, reward: torch.Tensor) -> None:
        if self.actions is None:  # the first step (an end check's)
            self.actions = torch.empty(
                (self.obs.shape[0], self.total, *actions.shape[1:]),
                dtype=actions.dtype,
                device=self.device,
            )
            self.rows.append(self.actions.unbind(0))
        obs_rows, reward_rows, action_rows = self.rows
        obs_rows[t].copy_(obs)
        action_rows[t].copy_(actions)
        reward_rows[t].copy_(reward)

    def taken(self, steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        assert self.actions is not None, "a batch takes at least one step"
        return self.obs[:steps], self.actions[:steps], self.rewards[:steps]


class _RandomActions:
    """Uniformly random actions for the copies ``chosen`` [N] from their own decision draws
    (a faulty actuator), the others' actions kept: a mask, the same shapes at every step."""

    def __init__(self, chosen: torch.Tensor, space: gym.Space | None, device: torch.device):
        self.chosen = chosen
        self.space = space
        self.low = self.high = None
        if isinstance(space, gym.spaces.Box) and space.is_bounded():
            self.low = torch.as_tensor(space.low, dtype=torch.float32, device=device)
            self.high = torch.as_tensor(space.high, dtype=torch.float32, device=device)
        elif not isinstance(space, gym.spaces.Discrete):
            raise ValueError(f"random actions need a Discrete or bounded Box space, got {space}")

    def __call__(self, actions: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``actions`` [N, ...] with the chosen copies' replaced, from ``u`` [N, k]."""
        if self.low is not None and self.high is not None:
            low, high = self.low, self.high
            drawn = low + u[:, : low.numel()].reshape(-1, *low.shape) * (high - low)
        else:
            assert isinstance(self.space, gym.spaces.Discrete)
            n, first = int(self.space.n), int(self.space.start)
            drawn = (u[:, 0] * n).long().clamp_max(n - 1) + first
        mask = self.chosen.reshape(-1, *([1] * (actions.dim() - 1)))
        return torch.where(mask, drawn.to(actions.dtype), actions)


def _random_actions(
    actions: torch.Tensor,
    chosen: torch.Tensor,
    keys: torch.Tensor,
    step: int,
    k: int,
    space: gym.Space | None,
) -> torch.Tensor:
    """Uniformly random actions for the columns ``chosen`` at time ``step``, from the copies'
    decision draws (keys ``keys``, ``k`` draws a step): what the sampler's attackers take."""
    u = uniforms(keys.unsqueeze(1), (step * k + torch.arange(k, device=keys.device)).unsqueeze(0))
    return _RandomActions(chosen, space, keys.device)(actions, u)
