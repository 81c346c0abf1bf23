"""The observation spaces a policy is built for, and the ones flattened before it sees them.

A policy takes Discrete observations (a table), a 1-D Box (an MLP) or an image, a 3-D uint8
Box (a small CNN). Any other observation space (Dict, Tuple, MultiDiscrete, MultiBinary, a
Box of another shape) is flattened by gymnasium's rules into a 1-D Box: Box entries
concatenated, a Discrete one-hot, MultiBinary as it is.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np


def is_image(space: gym.Space) -> bool:
    """A 3-D uint8 Box: height × width × channels, or channels × height × width."""
    return (
        isinstance(space, gym.spaces.Box)
        and len(space.shape) == 3
        and np.dtype(space.dtype) == np.uint8
    )


def is_flattened(space: gym.Space) -> bool:
    """Whether observations of ``space`` are flattened before a policy sees them."""
    if isinstance(space, gym.spaces.Discrete) or is_image(space):
        return False
    return not (isinstance(space, gym.spaces.Box) and len(space.shape) == 1)


def policy_observation_space(space: gym.Space) -> gym.Space:
    """The space a policy sees for observations of ``space``; ValueError where gymnasium
    cannot flatten it (a Text or Graph space, a Sequence)."""
    if not is_flattened(space):
        return space
    try:
        flat = gym.spaces.flatten_space(space)
    except (NotImplementedError, TypeError, ValueError) as error:
        raise ValueError(f"observation space {space} cannot be flattened: {error}") from None
    if not isinstance(flat, gym.spaces.Box):
        raise ValueError(f"observation space {space} does not flatten into a Box")
    return flat
