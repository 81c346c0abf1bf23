"""One round of local updates of many agents, every agent at its own pace.

A lockstep round (every agent samples iteration i, then all take their step, then i + 1)
lasts, per iteration, as long as the longest of all the agents' episodes: with a thousand
agents of near-random policies most steps of the batch then serve a handful of long
episodes. Here each agent moves on as soon as its own batch is complete: its gradient is
taken (stacked with the other agents whose batch ended at the same step), it takes its ascent
step and starts its next batch right away, while the others keep sampling. The env copies
stay busy until agents run out of iterations.

Agent k's numbers still depend on agent k alone: its env seed and action uniforms come from
its own generator at its own local steps, and the gradient of its batch is the same in any
company (:mod:`fedhpg.common.batched.mlp`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fedhpg.common.batched import mlp
from fedhpg.common.batched.coefficients import returns as copy_returns
from fedhpg.common.batched.maths import NUMPY, PolicyMaths
from fedhpg.common.batched.sampler import UNIFORM_CHUNK, Batches, _groups
from fedhpg.common.local import LocalTally
from fedhpg.envs.multi import MultiBatchEnv, block_columns

GradientStep = Callable[[Batches, np.ndarray, np.ndarray], np.ndarray]
"""(the finished batches, their agents' positions, the steps each has taken this round) ->
which of them had their gradient clipped; afterwards ``params`` holds their new θ rows."""


@dataclass
class RoundTiming:
    """Where a round's thread CPU time went: sampling (env steps, forwards, draws, narrowing)
    and gradients (extracting finished batches, gradients, steps, restarts)."""

    sample_s: float = 0.0
    gradient_s: float = 0.0


MAX_WAIT = 8
"""Steps an agent whose batch ended may wait for company before its gradient is taken: one
stacked gradient for many agents costs about what one costs alone."""


class _Frame:
    """The agents a round still steps, laid out densely: their env copies, observations,
    flags, uniforms and recent steps, and one stacked forward per run of agents with equal
    copy counts. Rebuilt (narrowed) when half of its agents are done, so that every
    per-step operation is a contiguous one over the copies still in use."""

    def __init__(
        self,
        agents: np.ndarray,
        counts: np.ndarray,
        env: MultiBatchEnv,
        ring: int,
        obs_shape: tuple[int, ...],
    ) -> None:
        self.agents = agents  # round positions, increasing
        self.counts = counts[agents]
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        size = int(self.offsets[-1])
        self.owner = np.repeat(np.arange(len(agents)), self.counts)  # frame-local
        self.env = env
        self.obs = np.zeros((size, *obs_shape), dtype=np.float32)
        self.running = np.zeros(size, dtype=bool)
        self.success = np.zeros(size, dtype=bool)
        self.uniforms = np.zeros((UNIFORM_CHUNK, size))
        self.ring = _Rings(ring, (size, *obs_shape))
        self.runs = [(s, e, size) for s, e, size in _groups(self.counts)]
        self.layers: list[Any] = []

    def narrowed(self, keep: np.ndarray, since: int, now: int) -> _Frame:
        """The frame of the local agents ``keep``, carrying their state and the ring's slots
        ``since`` … ``now`` − 1 (the batches in progress)."""
        columns = block_columns(self.offsets, keep)
        counts = np.zeros(int(self.agents.max()) + 1, dtype=np.int64)
        counts[self.agents] = self.counts
        frame = _Frame(self.agents[keep], counts, self.env.subset(keep), self.ring.bound,
                       self.obs.shape[1:])  # fmt: skip
        frame.obs[:] = self.obs[columns]
        frame.running[:] = self.running[columns]
        frame.success[:] = self.success[columns]
        frame.uniforms[:] = self.uniforms[:, columns]
        frame.ring = self.ring.narrowed(columns, since, now)
        return frame

    def load(self, params: np.ndarray, shape: mlp.MLPShape, maths: PolicyMaths) -> None:
        self.layers = [
            maths.unflatten(shape, params[self.agents[start:end]]) for start, end, _ in self.runs
        ]

    def refresh(
        self, params: np.ndarray, shape: mlp.MLPShape, changed: np.ndarray, maths: PolicyMaths
    ) -> None:
        """Reload the layers of the local agents ``changed`` after their step."""
        for (start, end, _), layers in zip(self.runs, self.layers, strict=True):
            rows = changed[(changed >= start) & (changed < end)]
            if len(rows):
                fresh = maths.unflatten(shape, params[self.agents[rows]])
                maths.assign(layers, rows - start, fresh)


def run_round(
    env: MultiBatchEnv,
    shape: mlp.MLPShape,
    params: np.ndarray,
    rngs: Sequence[np.random.Generator],
    horizons: Sequence[int],
    iterations: Sequence[int],
    gradient_step: GradientStep,
    on_batch: Callable[[int, int, int, float], None] | None = None,
    timing: RoundTiming | None = None,
    maths: PolicyMaths = NUMPY,
) -> list[LocalTally]:
    """Every agent (env block a, θ row ``params[a]``) runs ``iterations[a]`` local iterations.

    ``on_batch(position, iteration, env_steps, compute_s)`` follows each agent's step;
    ``timing`` receives the round's split of CPU time; ``maths`` does the policy's forwards.
    """
    counts = np.asarray(env.counts)
    num_agents = len(counts)
    horizon_of = np.asarray(horizons, dtype=np.int64)
    ring = int(horizon_of.max()) + MAX_WAIT + 1
    tallies = [LocalTally() for _ in range(num_agents)]
    done = np.zeros(num_agents, dtype=np.int64)  # local iterations taken this round
    local_step = np.zeros(num_agents, dtype=np.int64)
    started_at = np.zeros(num_agents, dtype=np.int64)
    waiting_since = np.zeros(num_agents, dtype=np.int64)
    working = np.asarray(iterations) > 0
    sampling = working.copy()
    cpu_started = time.thread_time()
    steps_so_far = 0
    gradient_s = 0.0
    obs_shape = tuple(env.single_observation_space.shape or ())
    everyone = np.nonzero(working)[0]
    frame = _Frame(everyone, counts, env if len(everyone) == num_agents else env.subset(everyone),
                   ring, obs_shape)  # fmt: skip

    def start(local: np.ndarray, now: int) -> None:
        agents = frame.agents[local]
        seeds = [int(rngs[a].integers(2**63 - 1)) for a in agents]
        columns = block_columns(frame.offsets, local)
        frame.obs[columns] = frame.env.reset(seeds, local)
        frame.running[columns] = True
        frame.success[columns] = False
        local_step[agents] = 0
        started_at[agents] = now
        sampling[agents] = True

    def finish(local: np.ndarray, now: int) -> None:
        """Gradients and steps of the agents whose batches ended; restart those not done."""
        nonlocal steps_so_far, gradient_s
        entered = time.thread_time()
        agents = frame.agents[local]
        batches = frame.ring.ended(local, local_step[agents], started_at[agents],
                                   frame.offsets, frame.counts)  # fmt: skip
        clipped = gradient_step(batches, agents, done[agents])
        frame.refresh(params, shape, local, maths)
        steps = batches.env_steps()
        returns = np.add.reduceat(copy_returns(batches), batches.offsets[:-1])
        steps_so_far += int(steps.sum())
        cpu_per_step = (time.thread_time() - cpu_started) / max(steps_so_far, 1)
        for i, a in enumerate(agents):
            compute_s = cpu_per_step * int(steps[i])
            tallies[a].add_counts(int(counts[a]), int(steps[i]), float(returns[i]),
                                  compute_s=compute_s, clipped=bool(clipped[i]))  # fmt: skip
            if on_batch is not None:
                on_batch(int(a), int(done[a]), int(steps[i]), compute_s)
        done[agents] += 1
        working[agents] = done[agents] < np.asarray(iterations)[agents]
        again = local[working[agents]]
        if len(again):
            start(again, now)
        gradient_s += time.thread_time() - entered

    frame.load(params, shape, maths)
    start(np.arange(len(frame.agents)), 0)
    now = 0
    while working.any():
        still = working[frame.agents]
        if 2 * int(still.sum()) <= len(still):
            keep = np.nonzero(still)[0]
            since = int(started_at[frame.agents[keep]].min())
            frame = frame.narrowed(keep, since, now)
            frame.load(params, shape, maths)
        agents = frame.agents
        active = np.nonzero(sampling[agents])[0]
        in_flight = working[agents]
        frame.ring.ensure(int(started_at[agents[in_flight]].min()), now)
        for j in active[local_step[agents[active]] % UNIFORM_CHUNK == 0]:
            frame.uniforms[:, frame.offsets[j] : frame.offsets[j + 1]] = rngs[agents[j]].random(
                (UNIFORM_CHUNK, int(frame.counts[j]))
            )
        copy_step = local_step[agents][frame.owner]
        obs = frame.obs
        actions = np.empty(len(obs), dtype=np.int64)
        chunk_row = copy_step % UNIFORM_CHUNK
        for (start_agent, end_agent, size), layers in zip(frame.runs, frame.layers, strict=True):
            rows = slice(frame.offsets[start_agent], frame.offsets[end_agent])
            num = end_agent - start_agent
            actions[rows] = maths.act(
                layers,
                obs[rows].reshape(num, size, -1),
                frame.uniforms[chunk_row[rows], np.arange(rows.start, rows.stop)],
            )
        running = frame.running
        step = frame.env.step(actions)
        frame.ring.record(now, obs, actions, step.reward * running, running)
        frame.success |= running & step.success
        running &= ~(step.terminated | step.truncated)
        frame.obs = step.obs
        local_step[agents[active]] += 1
        running &= (copy_step + 1) < horizon_of[agents][frame.owner]
        now += 1
        batch_running = np.logical_or.reduceat(running, frame.offsets[:-1])
        ended = active[~batch_running[active]]
        if len(ended):
            sampling[agents[ended]] = False
            waiting_since[agents[ended]] = now
        waiting = np.nonzero(working[agents] & ~sampling[agents])[0]
        if len(waiting) and (
            len(waiting) >= max(8, len(active) // 8)
            or now - int(waiting_since[agents[waiting]].min()) >= MAX_WAIT
            or not sampling[agents].any()
        ):
            finish(waiting, now)
    if timing is not None:
        timing.gradient_s = gradient_s
        timing.sample_s = time.thread_time() - cpu_started - gradient_s
    return tallies


class _Rings:
    """The recent steps of every copy of a frame, indexed by step number modulo ``size``.

    A batch in progress is at most horizon + MAX_WAIT steps old; the ring starts small and
    doubles (up to that bound) when a batch grows long, so short episodes cost little memory.
    """

    START = 64

    def __init__(self, bound: int, obs_shape: tuple[int, ...], size: int = START) -> None:
        self.bound = bound
        self.size = min(size, bound)
        self.obs_shape = obs_shape
        num_envs = obs_shape[0]
        self.obs = np.zeros((self.size, *obs_shape), dtype=np.float32)
        self.actions = np.zeros((self.size, num_envs), dtype=np.int64)
        self.rewards = np.zeros((self.size, num_envs), dtype=np.float64)
        self.alive = np.zeros((self.size, num_envs), dtype=bool)

    def _arrays(self) -> tuple[np.ndarray, ...]:
        return self.obs, self.actions, self.rewards, self.alive

    def ensure(self, oldest: int, now: int) -> None:
        """Make room for steps ``oldest`` … ``now`` (the batches in flight, and this step)."""
        needed = now - oldest + 1 + MAX_WAIT
        if needed <= self.size or self.size == self.bound:
            return
        grown = _Rings(self.bound, self.obs_shape, max(2 * self.size, needed))
        steps = np.arange(oldest, now)
        for mine, theirs in zip(grown._arrays(), self._arrays(), strict=True):
            mine[steps % grown.size] = theirs[steps % self.size]
        self.__dict__.update(grown.__dict__)

    def record(
        self, step: int, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
        alive: np.ndarray,
    ) -> None:  # fmt: skip
        slot = step % self.size
        self.obs[slot] = obs
        self.actions[slot] = actions
        self.rewards[slot] = rewards
        self.alive[slot] = alive

    def narrowed(self, columns: np.ndarray, since: int, now: int) -> _Rings:
        part = _Rings(self.bound, (len(columns), *self.obs_shape[1:]), self.size)
        slots = np.arange(since, now) % self.size
        for mine, theirs in zip(part._arrays(), self._arrays(), strict=True):
            mine[slots] = theirs[slots][:, columns]
        return part

    def ended(
        self,
        agents: np.ndarray,
        lengths: np.ndarray,
        started_at: np.ndarray,
        offsets: np.ndarray,
        counts: np.ndarray,
    ) -> Batches:
        """The ended batches of the frame's ``agents``: every step (agent, t, copy) read once
        from the ring by flat index; observations and actions of the alive steps only."""
        sizes = counts[agents]
        sub_offsets = np.concatenate([[0], np.cumsum(sizes)])
        width = int(sub_offsets[-1])
        cells = lengths * sizes
        agent = np.repeat(np.arange(len(agents)), cells)
        within = np.arange(int(cells.sum())) - np.repeat(np.cumsum(cells) - cells, cells)
        size = sizes[agent]
        t, b = within // size, within % size
        source = (
            ((started_at[agent] + t) % self.size) * self.obs.shape[1] + offsets[agents][agent] + b
        )
        target = t * width + sub_offsets[agent] + b
        shape = (int(lengths.max()), width)
        rewards = np.zeros(shape, dtype=np.float64)
        alive = np.zeros(shape, dtype=bool)
        rewards.reshape(-1)[target] = self.rewards.reshape(-1)[source]
        alive_cells = self.alive.reshape(-1)[source]
        alive.reshape(-1)[target] = alive_cells
        kept = np.nonzero(alive_cells)[0]
        features = self.obs.shape[2:]
        return Batches(
            rewards=rewards,
            alive=alive,
            offsets=sub_offsets,
            lengths=lengths.copy(),
            row_agent=agent[kept],
            row_cell=target[kept],
            obs=self.obs.reshape(-1, *features)[source[kept]],
            actions=self.actions.reshape(-1)[source[kept]],
        )
