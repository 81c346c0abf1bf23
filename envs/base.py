"""The environment interface the rollout sampler steps, and per-agent environment variants.

A *family* (GridWorld, CartPole, ...) generates K *variants*: environments with identical
observation and action spaces but their own rewards, dynamics and discount factor, one per
agent. The sampler never steps a single environment: it steps a :class:`BatchEnv` of B copies
of one variant with one array of actions.
"""

from __future__ import annotations

import abc
import hashlib
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np


class BatchStep(NamedTuple):
    """What one batched step returns; every array has leading dimension ``num_envs``."""

    obs: np.ndarray
    reward: np.ndarray  # float64
    terminated: np.ndarray  # bool
    truncated: np.ndarray  # bool
    success: np.ndarray  # bool: the episode ended in the task's goal (False if no such notion)


@runtime_checkable
class BatchEnv(Protocol):
    """B copies of one environment variant stepped together.

    Each copy runs one episode after :meth:`reset`. Once a copy has terminated or been
    truncated its later outputs are unspecified: the sampler masks them out, so an
    implementation may keep stepping, reset, or freeze that copy, whichever is cheapest.
    """

    @property
    def num_envs(self) -> int: ...

    @property
    def single_observation_space(self) -> gym.Space: ...

    @property
    def single_action_space(self) -> gym.Space: ...

    def reset(self, *, seed: int) -> np.ndarray:
        """Start one episode in every copy; ``seed`` fixes all randomness of the batch."""
        ...

    def step(self, actions: np.ndarray) -> BatchStep:
        """Apply one action per copy."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True, kw_only=True)
class EnvVariant(abc.ABC):
    """One agent's environment: the same spaces as its siblings, its own MDP and discount."""

    has_goal: ClassVar[bool] = False
    """Whether episodes can end in a goal (``BatchStep.success``); else a success rate means
    nothing and reports leave it out."""

    family: str
    index: int
    gamma: float
    params: dict[str, Any] = field(default_factory=dict)

    @abc.abstractmethod
    def make_env(self, *, render_mode: str | None = None) -> gym.Env:
        """A single gymnasium environment of this variant (for checks, rendering, users)."""

    @abc.abstractmethod
    def make_batch_env(self, num_envs: int) -> BatchEnv:
        """B copies of this variant for the sampler."""

    @property
    @abc.abstractmethod
    def max_episode_steps(self) -> int:
        """The step limit of one episode (the horizon H unless the run asks for less)."""

    def digest(self) -> str:
        """A fingerprint of everything that makes this variant's MDP: two hosts that built the
        same variant (same generator, seed, level, library versions) agree on it. The dataclass
        repr holds every field, floats written exactly."""
        return hashlib.sha256(repr(self).encode()).hexdigest()[:32]

    def signature(self) -> dict[str, str]:
        """What must agree across agents: the observation and action spaces."""
        env = self.make_env()
        try:
            return space_signature(env.observation_space, env.action_space)
        finally:
            env.close()


def space_signature(observation_space: gym.Space, action_space: gym.Space) -> dict[str, str]:
    """A comparable description of a pair of spaces (shape, dtype, bounds, sizes)."""
    return {
        "observation": describe_space(observation_space),
        "action": describe_space(action_space),
    }


def describe_space(space: gym.Space) -> str:
    if isinstance(space, gym.spaces.Discrete):
        return f"Discrete({int(space.n)}, start={int(space.start)})"
    if isinstance(space, gym.spaces.Box):
        low = np.array2string(np.unique(space.low), precision=6, threshold=8)
        high = np.array2string(np.unique(space.high), precision=6, threshold=8)
        return f"Box(shape={space.shape}, dtype={space.dtype}, low={low}, high={high})"
    return repr(space)
