"""Sampling: one episode in every copy of every block, all blocks stepped together.

Block b holds ``counts[b]`` copies of one row's environment (its trajectories this
iteration); every copy's randomness comes from its own trajectory key (its reset from counters
−1, −2, …, its decisions from counters t · noise_size + j, its environment's own draws at step
t, where a family has them, from :data:`ENV_COUNTERS` − t · step_noise − j), so a trajectory
is the same in any company and any layout.

Every step is the same function of the batch's shapes alone: every copy acts, in one call of
the policy on a grid of tiles (:class:`_Grid`, each tile one block's copies under its θ row),
every copy is stepped (the torch families; gymnasium's batch environments skip the blocks
whose copies have all ended), and a copy whose episode has ended is masked out (``running``),
never recorded as alive. Nothing inside a step waits for the device: every :data:`END_CHECK`
steps the sampler asks how many tiles still hold a running copy, stops when none does, and
once at most :data:`NARROW_AT` of the tiles do, drops the others (every copy of a tile whose
copies have all ended: the policy's calls keep their tiles' shapes, so no float changes); the
batch's length (its longest episode) is read once at the end. Between two checks a step holds
no data-dependent shape, no index found on the host and no allocation (the record buffers
grow at the checks only), so a GPU runs it without waiting, and each width's step could be
captured as one graph. With short episodes of very different lengths (a policy that has not
learnt yet) the narrowing is what keeps a step's cost near the copies that may still run.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from functools import cached_property

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
from fedhpg.envs.tensor_writes import put_distinct


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
"""Steps between two checks of which tiles still hold a running copy (the sampler's only
waits for the device while it steps, and the only steps where the batch narrows). A batch
steps at most ``END_CHECK − 1`` steps past its longest episode, whose results are masked and
cut off; :data:`RECORD_START` is a multiple of it, so the record buffers grow at checks
only."""


NARROW_AT = 0.75
"""At an end check, the batch narrows to the tiles of copies that still run once they are at
most this share of the tiles stepped (every copy of a tile whose copies have all ended
dropped): a step then costs what the copies that may still run cost. The drop's gathers
cost about a step, so a narrowing that would save little is not made."""


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
    its own observation, draws and θ row alone: which copies share its tile, and how many
    tiles a call takes, does not change it."""

    def __init__(
        self,
        policy: PolicyRows,
        counts: list[int] | np.ndarray,
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
        self.real = len(block_of_tile)
        """Tiles that hold copies (the first ones)."""
        self.copy_of_slot, self.valid = grid, valid
        """Each real tile's copies ([real, ACT_TILE], padding repeats a copy) and which slots
        hold their own copy."""
        self.block_theta, self.block_of_tile = theta, block_of_tile
        self.tiles_per_call = tiles_per_call
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

    def running_tiles(self, running: torch.Tensor) -> torch.Tensor:
        """[real] whether each real tile holds a copy that still runs (on the device)."""
        if self.index is None:
            return running.view(self.tiles, ACT_TILE).any(1)
        return (running[self.index[: self.real]] & self.flags).any(1)

    @cached_property
    def flags(self) -> torch.Tensor:
        """[real, ACT_TILE] the real tiles' slots that hold their own copy, on the device."""
        return torch.from_numpy(self.valid).to(self.block_theta.device)

    def narrowed(self, kept_tiles: np.ndarray) -> tuple[_Grid, np.ndarray]:
        """The grid of the tiles ``kept_tiles`` (increasing) alone, each its own block, and
        the copies they hold (increasing): the kept copies are the new grid's 0 … m − 1."""
        valid = self.valid[kept_tiles]
        copies = self.copy_of_slot[kept_tiles][valid]
        theta = self.block_theta[torch.from_numpy(self.block_of_tile[kept_tiles])]
        return _Grid(self.policy, valid.sum(1), theta, self.tiles_per_call), copies

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
    record = _Record(total, obs, device)
    flipped = None
    if faults is not None and bool(faults.flipped_rewards.any()):
        flipped = faults.flipped_rewards[owner]
    randomised = None
    if faults is not None and not greedy and bool(faults.random_actions.any()):
        randomised = _RandomActions(faults.random_actions[owner], action_space, device)
    now = _Stepped(
        obs=obs,
        running=torch.ones(total, dtype=torch.bool, device=device),
        lengths=torch.zeros(total, dtype=torch.int64, device=device),
        success=torch.zeros(total, dtype=torch.bool, device=device),
        keyed=keys.unsqueeze(1),
        stop_at=horizons[owner] if bool((horizons < horizon).any()) else None,
        randomised=randomised,
    )  # stop_at: each copy's horizon, where the rows' differ (else the loop's bound is theirs)
    k = policy.noise_size
    draws_at = torch.arange(NOISE_CHUNK * k, device=device).unsqueeze(0)
    env_noise = copies.step_noise
    env_at = ENV_COUNTERS - torch.arange(ENV_CHUNK * env_noise, device=device).unsqueeze(0)
    noise: tuple[torch.Tensor, ...] = ()  # the chunk's decision draws, a grid per step
    copy_noise: tuple[torch.Tensor, ...] = ()  # the same, [N, k] per step (attackers' draws)
    narrowing = _Narrowing(now)
    t = 0
    with torch.no_grad():
        while t < horizon:
            if t % end_check == 0:
                if t:  # the step's only wait, every end_check
                    tiles_running = grid.running_tiles(now.running)
                    live = int(tiles_running.sum())
                    if not live:
                        break
                    if copies.narrows and live <= NARROW_AT * grid.real:
                        kept = np.flatnonzero(tiles_running.cpu().numpy())
                        grid, kept_copies = grid.narrowed(kept)
                        keep = torch.from_numpy(kept_copies).to(device)
                        now = narrowing.keep(now, keep, t)
                        copies.keep(keep)
                        record.columns = narrowing.columns
                        if now.drawn is not None:  # the rest of the chunk's draws
                            noise = grid.draws(now.drawn.transpose(0, 1)).unbind(0)
                            copy_noise = now.drawn.unbind(1) if now.randomised else ()
                record.reserve(t + end_check)
            if t % NOISE_CHUNK == 0 and not greedy:
                count = now.keyed.shape[0]
                drawn = uniforms(now.keyed, draws_at + t * k).view(count, NOISE_CHUNK, k)
                noise = grid.draws(drawn.transpose(0, 1)).unbind(0)
                copy_noise = drawn.unbind(1) if now.randomised else ()
                now.drawn = drawn
            if env_noise and t % ENV_CHUNK == 0:
                # step t + s, draw j: counter ENV_COUNTERS − (t + s)·s_n − j
                now.env_draws = uniforms64(now.keyed, env_at - t * env_noise).view(
                    now.keyed.shape[0], ENV_CHUNK, env_noise
                )
            at = t % NOISE_CHUNK
            actions = grid.act(now.obs, noise[at] if noise else None)
            if now.randomised is not None:
                actions = now.randomised(actions, copy_noise[at])
            env_draws = None if now.env_draws is None else now.env_draws[:, t % ENV_CHUNK]
            step = copies.step(actions, now.running, env_draws)
            record.add(t, now.obs, actions, step.reward)
            running = now.running
            now.lengths += running
            now.success |= running & step.success
            running.masked_fill_(step.terminated | step.truncated, False)
            t += 1
            if now.stop_at is not None:
                running &= now.stop_at > t
            now.obs = step.obs
    lengths, success = narrowing.every_copy(now)
    steps = int(lengths.max())  # the batch's longest episode: its length
    alive = torch.arange(steps, device=device).unsqueeze(1) < lengths
    obs_seen, actions_taken, rewards = record.taken(steps)
    rewards.masked_fill_(~alive, 0.0)  # the record's own buffer: zeroed where nothing ran
    if narrowing.first is not None:  # the dropped copies' cells were never written: zeros
        dead = ~alive[narrowing.first :]
        for values in (obs_seen[narrowing.first :], actions_taken[narrowing.first :]):
            values.masked_fill_(dead.view(*dead.shape, *[1] * (values.dim() - 2)), 0)
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


@dataclass
class _Stepped:
    """What the sampler holds of each copy it steps, [M, ...] each (narrowed together)."""

    obs: torch.Tensor
    running: torch.Tensor
    lengths: torch.Tensor
    success: torch.Tensor
    keyed: torch.Tensor
    """[M, 1] the copies' trajectory keys."""
    stop_at: torch.Tensor | None
    randomised: _RandomActions | None
    drawn: torch.Tensor | None = None
    """The decision draws of the current chunk, [M, NOISE_CHUNK, k]."""
    env_draws: torch.Tensor | None = None
    """The environments' draws of the current chunk, [M, ENV_CHUNK, s]."""

    def kept(self, keep: torch.Tensor) -> _Stepped:
        """The copies ``keep`` alone."""

        def part(values: torch.Tensor | None) -> torch.Tensor | None:
            return None if values is None else values[keep]

        return _Stepped(
            obs=self.obs[keep],
            running=self.running[keep],
            lengths=self.lengths[keep],
            success=self.success[keep],
            keyed=self.keyed[keep],
            stop_at=part(self.stop_at),
            randomised=None if self.randomised is None else self.randomised.kept(keep),
            drawn=part(self.drawn),
            env_draws=part(self.env_draws),
        )


class _Narrowing:
    """Every copy's length and success, kept for the copies a narrowing drops (the sampler
    carries on with the kept copies' own)."""

    def __init__(self, stepped: _Stepped) -> None:
        self.lengths, self.success = stepped.lengths, stepped.success
        self.columns: torch.Tensor | None = None
        """The batch's column of each copy still stepped (None: copy n is column n)."""
        self.first: int | None = None
        """The step of the first narrowing (None: none yet)."""

    def keep(self, stepped: _Stepped, keep: torch.Tensor, t: int) -> _Stepped:
        """Record the ``stepped`` copies' lengths and successes at step ``t``; the copies
        ``keep`` of them, which alone go on."""
        self._store(stepped)
        self.columns = keep if self.columns is None else self.columns[keep]
        self.first = t if self.first is None else self.first
        return stepped.kept(keep)

    def _store(self, stepped: _Stepped) -> None:
        if self.columns is None:
            self.lengths, self.success = stepped.lengths, stepped.success
        else:
            put_distinct(self.lengths, self.columns, stepped.lengths)
            put_distinct(self.success, self.columns, stepped.success)

    def every_copy(self, stepped: _Stepped) -> tuple[torch.Tensor, torch.Tensor]:
        """Every column's length and success, the ``stepped`` copies' included."""
        self._store(stepped)
        return self.lengths, self.success


class _Record:
    """The steps taken so far, time-major, in buffers that double as episodes grow (a batch
    of short episodes never holds a horizon's worth of memory), at the end checks only. A
    step writes the raw results of every copy stepped, whether it runs or not, so the
    buffers are never filled beforehand; the sampler zeroes at the end the rewards of the
    steps that did not happen and, from the first narrowing on (the dropped copies' cells are
    never written), their observations and actions too. Every step's rows are views made
    when the buffers are: until the batch narrows a step writes its views whole, then the
    kept copies' columns of them."""

    def __init__(self, total: int, obs: torch.Tensor, device: torch.device) -> None:
        self.total, self.device = total, device
        self.obs = torch.empty((RECORD_START, *obs.shape), dtype=obs.dtype, device=device)
        self.actions: torch.Tensor | None = None
        self.rewards = torch.empty((RECORD_START, total), dtype=torch.float64, device=device)
        self.rows: list[tuple[torch.Tensor, ...]] = []
        """Each buffer's rows (obs, rewards, then actions once their type is known)."""
        self.columns: torch.Tensor | None = None
        """The column of each copy a step writes (None: copy n writes column n; after a
        narrowing, :attr:`_Narrowing.columns`)."""

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
        if self.columns is None:
            obs_rows[t].copy_(obs)
            action_rows[t].copy_(actions)
            reward_rows[t].copy_(reward)
        elif self.device.type == "cpu":
            obs_rows[t].index_copy_(0, self.columns, obs)
            action_rows[t].index_copy_(0, self.columns, actions)
            reward_rows[t].index_copy_(0, self.columns, reward)
        else:  # each column named once: no deterministic sort needed
            for row, values in ((obs_rows[t], obs), (action_rows[t], actions),
                                (reward_rows[t], reward)):  # fmt: skip
                put_distinct(row, self.columns, values)

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

    def kept(self, keep: torch.Tensor) -> _RandomActions:
        """The same for the copies ``keep`` alone."""
        narrowed = copy.copy(self)
        narrowed.chosen = self.chosen[keep]
        return narrowed

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
