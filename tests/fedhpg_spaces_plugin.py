"""Gymnasium ids with the spaces no environment shipped with gymnasium has: a Dict observation,
MultiDiscrete and MultiBinary actions (``plugins=[fedhpg_spaces_plugin]``).

``spaces/Beacon-v0``: a beacon lights one of ``width`` lamps; the observation is a Dict of
the lit lamp (Discrete) and a noisy reading of the step (Box). Every component of the action
earns 1 when it names the lit lamp (for MultiBinary: when component ``lit`` is 1 and every
other 0, each component scored on its own). Episodes last 10 steps.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

STEPS = 10


class Beacon(gym.Env[dict[str, Any], Any]):
    """Name the lit lamp: a Dict observation and Discrete, MultiDiscrete or MultiBinary actions.

    ## Action Space
    ``action="discrete"``: Discrete(width); ``"multi_discrete"``: MultiDiscrete([width] * 3);
    ``"multi_binary"``: MultiBinary(width).

    ## Observation Space
    Dict(lit: Discrete(width), clock: Box(0, 1, (1,))).

    ## Rewards
    One per action component that matches the lit lamp.
    """

    def __init__(
        self, width: int = 3, action: str = "discrete", render_mode: str | None = None
    ) -> None:
        self.render_mode = render_mode
        self.width = width
        self.kind = action
        self.observation_space = gym.spaces.Dict(
            {
                "lit": gym.spaces.Discrete(width),
                "clock": gym.spaces.Box(0.0, 1.0, shape=(1,), dtype=np.float32),
            }
        )
        spaces: dict[str, gym.Space[Any]] = {
            "discrete": gym.spaces.Discrete(width),
            "multi_discrete": gym.spaces.MultiDiscrete([width] * 3),
            "multi_binary": gym.spaces.MultiBinary(width),
        }
        self.action_space = spaces[action]
        self._lit = 0
        self._step = 0

    def _observation(self) -> dict[str, Any]:
        clock = np.array([self._step / STEPS], dtype=np.float32)
        return {"lit": self._lit, "clock": clock}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        self._lit = int(self.np_random.integers(self.width))
        self._step = 0
        return self._observation(), {}

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        chosen = np.asarray(action).reshape(-1)
        if self.kind == "multi_binary":
            target = np.eye(self.width, dtype=np.int64)[self._lit]
            reward = float(np.sum(chosen == target))
        else:
            reward = float(np.sum(chosen == self._lit))
        self._step += 1
        self._lit = int(self.np_random.integers(self.width))
        return self._observation(), reward, False, False, {}


if "spaces/Beacon-v0" not in gym.registry:
    gym.register(
        id="spaces/Beacon-v0", entry_point="fedhpg_spaces_plugin:Beacon", max_episode_steps=STEPS
    )
