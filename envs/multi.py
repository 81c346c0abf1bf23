"""Environment copies of many agents stepped as one batch: the batched engine's environment.

A :class:`MultiBatchEnv` holds, for agents a = 0 … A−1 in order, a contiguous block of
``counts[a]`` copies of agent a's variant (its B_k trajectories). Block a is reset from agent
a's own seed, so what happens in a block never depends on the other blocks: agent k's
trajectories are the same whether it is stepped alone or beside 999 others. That holds by
construction for :class:`GroupedBatchEnv` (each block its own :class:`BatchEnv`), and for
:class:`CartPoleMulti` because its dynamics are elementwise numpy operations (each copy's
arithmetic is its own, IEEE-exact, and numpy's SIMD loops give a lane the same bits wherever
it sits in an array) with the per-copy physics held in arrays.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import Protocol

import gymnasium as gym
import numpy as np

from fedhpg.envs.base import BatchEnv, BatchStep, EnvVariant

Blocks = Sequence[int] | np.ndarray
"""Block numbers (increasing)."""


class MultiBatchEnv(Protocol):
    """Blocks of copies of several variants stepped together (see the module docstring)."""

    @property
    def counts(self) -> Sequence[int]: ...

    @property
    def num_envs(self) -> int: ...

    @property
    def single_observation_space(self) -> gym.Space: ...

    @property
    def single_action_space(self) -> gym.Space: ...

    def reset(self, seeds: Sequence[int], blocks: Blocks | None = None) -> np.ndarray:
        """Start one episode in every copy of ``blocks`` (None: all), block ``blocks[i]``'s
        randomness from ``seeds[i]``; their first observations, in order."""
        ...

    def step(self, actions: np.ndarray, blocks: np.ndarray | None = None) -> BatchStep:
        """One action per copy of ``blocks`` (increasing block numbers; None: all), in
        order; the other blocks are left as they are."""
        ...

    def subset(self, blocks: np.ndarray) -> MultiBatchEnv:
        """The blocks ``blocks`` (increasing) as a batch of their own, in their current state
        (sharing this batch's envs: close only the original)."""
        ...

    def close(self) -> None: ...


def block_offsets(counts: Sequence[int]) -> np.ndarray:
    """[A + 1] start offsets of the blocks (the last is the number of copies)."""
    return np.concatenate([[0], np.cumsum(np.asarray(counts, dtype=np.int64))])


def kept_blocks(counts: Sequence[int], blocks: np.ndarray) -> tuple[list[int], np.ndarray, int]:
    """(counts, offsets, copies) of the blocks ``blocks`` alone: a subset's layout."""
    kept = [counts[int(a)] for a in blocks]
    offsets = block_offsets(kept)
    return kept, offsets, int(offsets[-1])


def block_columns(offsets: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """The copies of ``blocks``, in block order."""
    sizes = offsets[blocks + 1] - offsets[blocks]
    starts = np.repeat(offsets[blocks] - np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes)
    return starts + np.arange(int(sizes.sum()))


class GroupedBatchEnv:
    """One :class:`BatchEnv` per block: any family, stepped block after block."""

    def __init__(self, variants: Sequence[EnvVariant], counts: Sequence[int]) -> None:
        self.counts = list(counts)
        self.offsets = block_offsets(counts)
        self.num_envs = int(self.offsets[-1])
        self.envs: list[BatchEnv] = [
            v.make_batch_env(n) for v, n in zip(variants, counts, strict=True)
        ]
        self.single_observation_space = self.envs[0].single_observation_space
        self.single_action_space = self.envs[0].single_action_space

    def reset(self, seeds: Sequence[int], blocks: Blocks | None = None) -> np.ndarray:
        chosen = range(len(self.envs)) if blocks is None else blocks
        return np.concatenate(
            [self.envs[a].reset(seed=int(s)) for a, s in zip(chosen, seeds, strict=True)]
        )

    def step(self, actions: np.ndarray, blocks: np.ndarray | None = None) -> BatchStep:
        chosen = range(len(self.envs)) if blocks is None else [int(a) for a in blocks]
        steps, row = [], 0
        for a in chosen:
            size = self.counts[a]
            steps.append(self.envs[a].step(actions[row : row + size]))
            row += size
        return BatchStep(*(np.concatenate(parts) for parts in zip(*steps, strict=True)))

    def subset(self, blocks: np.ndarray) -> GroupedBatchEnv:
        part = copy.copy(self)
        part.counts, part.offsets, part.num_envs = kept_blocks(self.counts, blocks)
        part.envs = [self.envs[int(a)] for a in blocks]
        return part

    def close(self) -> None:
        for env in self.envs:
            env.close()


CARTPOLE_PHYSICS = ("gravity", "masscart", "masspole", "total_mass", "length", "polemass_length",
                    "force_mag")  # fmt: skip
"""The attributes a CartPole variant sets (envs/families.py); any other one is not modelled
here, so such a variant falls back to :class:`GroupedBatchEnv`."""


class CartPoleMulti:
    """CartPole-v1 copies of many variants in one set of numpy arrays.

    The equations, constants, observation dtype and reset distribution are gymnasium's
    ``CartPoleVectorEnv`` (Euler integrator, thresholds 12° and 2.4, reward 1 per step,
    truncation at ``max_episode_steps``), with every physical constant a per-copy array; a
    block reset from seed s starts where gymnasium's vector env reset with seed s starts
    (tests/test_batched_engine.py checks both bit for bit). Copies past their episode's end
    keep being stepped (cheaper than masking); the sampler ignores them.
    """

    TAU = 0.02
    THETA_THRESHOLD = 12 * 2 * math.pi / 360
    X_THRESHOLD = 2.4

    def __init__(
        self,
        physics: Sequence[dict[str, float]],
        counts: Sequence[int],
        *,
        max_episode_steps: int = 500,
    ) -> None:
        self.counts = list(counts)
        self.offsets = block_offsets(counts)
        self.num_envs = int(self.offsets[-1])
        self.max_episode_steps = max_episode_steps
        repeats = np.asarray(counts, dtype=np.int64)
        stock = gym.make_vec("CartPole-v1", num_envs=1, vectorization_mode="vector_entry_point")
        try:
            self.single_observation_space = stock.single_observation_space
            self.single_action_space = stock.single_action_space
            defaults = {name: float(getattr(stock.unwrapped, name)) for name in CARTPOLE_PHYSICS}
        finally:
            stock.close()
        self.params = {
            name: np.repeat(np.array([p.get(name, defaults[name]) for p in physics]), repeats)
            for name in CARTPOLE_PHYSICS
        }
        self.state = np.zeros((4, self.num_envs))
        self.steps = np.zeros(self.num_envs, dtype=np.int32)
        self._success = np.zeros(self.num_envs, dtype=bool)
        self._copies_of: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self, seeds: Sequence[int], blocks: Blocks | None = None) -> np.ndarray:
        chosen = range(len(self.counts)) if blocks is None else blocks
        parts = []
        for a, seed in zip(chosen, seeds, strict=True):
            start, end = self.offsets[a], self.offsets[a + 1]
            # gymnasium's reset: np_random from the seed, then uniform(±0.05, size (4, n))
            rng = np.random.default_rng(int(seed))
            self.state[:, start:end] = rng.uniform(-0.05, 0.05, size=(4, end - start))
            self.steps[start:end] = 0
            parts.append(self.state[:, start:end].T.astype(np.float32))
        return np.concatenate(parts)

    def step(self, actions: np.ndarray, blocks: np.ndarray | None = None) -> BatchStep:
        copies: slice | np.ndarray = slice(None)
        if blocks is not None:
            if self._copies_of is None or self._copies_of[0] is not blocks:
                self._copies_of = (blocks, block_columns(self.offsets, blocks))
            copies = self._copies_of[1]
        p = {name: values[copies] for name, values in self.params.items()}
        x, x_dot, theta, theta_dot = self.state[:, copies]
        force = np.sign(actions - 0.5) * p["force_mag"]
        costheta = np.cos(theta)
        sintheta = np.sin(theta)
        temp = (force + p["polemass_length"] * np.square(theta_dot) * sintheta) / p["total_mass"]
        thetaacc = (p["gravity"] * sintheta - costheta * temp) / (
            p["length"] * (4.0 / 3.0 - p["masspole"] * np.square(costheta) / p["total_mass"])
        )
        xacc = temp - p["polemass_length"] * thetaacc * costheta / p["total_mass"]
        x = x + self.TAU * x_dot
        x_dot = x_dot + self.TAU * xacc
        theta = theta + self.TAU * theta_dot
        theta_dot = theta_dot + self.TAU * thetaacc
        state = np.stack((x, x_dot, theta, theta_dot))
        self.state[:, copies] = state
        terminated = (
            (x < -self.X_THRESHOLD)
            | (x > self.X_THRESHOLD)
            | (theta < -self.THETA_THRESHOLD)
            | (theta > self.THETA_THRESHOLD)
        )
        self.steps[copies] += 1
        truncated = self.steps[copies] >= self.max_episode_steps
        return BatchStep(
            obs=state.T.astype(np.float32),
            reward=np.ones(len(terminated), dtype=np.float64),
            terminated=terminated,
            truncated=truncated,
            success=self._success[copies],
        )

    def subset(self, blocks: np.ndarray) -> CartPoleMulti:
        columns = block_columns(self.offsets, blocks)
        part = copy.copy(self)
        part.counts, part.offsets, part.num_envs = kept_blocks(self.counts, blocks)
        part.params = {name: values[columns] for name, values in self.params.items()}
        part.state = self.state[:, columns]
        part.steps = self.steps[columns]
        part._success = self._success[columns]
        part._copies_of = None
        return part

    def close(self) -> None:
        pass


def cartpole_physics(variant: EnvVariant) -> dict[str, float] | None:
    """The variant's CartPole constants, or None if :class:`CartPoleMulti` cannot model it."""
    env_id = getattr(variant, "env_id", None)
    if env_id != "CartPole-v1":
        return None
    if getattr(variant, "env_kwargs", None) or getattr(variant, "action_cost", 0.0):
        return None
    if getattr(variant, "step_limit", 0) not in (0, 500):
        return None
    attributes: dict[str, float] = dict(getattr(variant, "attributes", {}))
    if not set(attributes) <= set(CARTPOLE_PHYSICS):
        return None
    return attributes


def make_multi_batch_env(variants: Sequence[EnvVariant], counts: Sequence[int]) -> MultiBatchEnv:
    """Blocks of ``counts[a]`` copies of ``variants[a]``: the native CartPole batch where
    every variant is a CartPole it models, else one batch env per block."""
    if len(variants) != len(counts) or not variants or min(counts) < 1:
        raise ValueError("one count >= 1 per variant is needed")
    physics = [cartpole_physics(v) for v in variants]
    if all(p is not None for p in physics):
        return CartPoleMulti([p for p in physics if p is not None], counts)
    return GroupedBatchEnv(variants, counts)
