"""What the compiled backend knows of its agents: the run, each agent's variant, budget,
discount and horizon (computed on first use: a host of 5,000 agents may see 500 of them in a
round), and the MLP's shape."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from fedhpg.common.algorithms.fedhpg import FedHPGBudget
from fedhpg.common.batched.mlp import MLPShape
from fedhpg.common.components import agent_profile
from fedhpg.common.config import RunConfig
from fedhpg.common.variants import discount, training_horizon
from fedhpg.envs.base import EnvVariant


class Lazy(dict[int, Any]):
    """A dict that computes a missing key's value once."""

    def __init__(self, make: Callable[[int], Any]) -> None:
        super().__init__()
        self.make = make

    def fill(self, keys: Iterable[int]) -> None:
        """Compute the values of ``keys`` not computed yet."""
        for key in keys:
            if key not in self:
                self[key] = self.make(key)

    def __missing__(self, key: int) -> Any:
        value = self[key] = self.make(key)
        return value


class EngineAgents:
    """The agents ``variants`` of a FedHPG run with the MLP categorical policy of ``shape``."""

    LARGE_TEMPORARIES = True
    """Megabytes allocated every round (common/runtime/memory.py tunes malloc for it)."""

    def __init__(self, run: RunConfig, variants: Mapping[int, EnvVariant], shape: MLPShape):
        self.run = run
        self.variants = variants
        self.shape = shape
        self.profiles = Lazy(lambda k: agent_profile(run, k))
        self.gammas = Lazy(lambda k: discount(run, variants[k]))
        self.horizons = Lazy(lambda k: training_horizon(run, variants[k]))

    def budget(self, k: int) -> FedHPGBudget:
        budget = self.profiles[k].budget
        assert isinstance(budget, FedHPGBudget), "the engines run FedHPG"
        return budget

    @property
    def indices(self) -> Sequence[int]:
        return sorted(self.variants)

    @property
    def num_params(self) -> int:
        return self.shape.num_params

    def prepare(self) -> None:
        """Every agent's profile, discount and horizon now (a host of 5,000 agents with 1,000
        of 10,000 training per round meets ~470 new agents a round, ~60 µs each, mostly
        the population's seeded draws of their budgets)."""
        for values in (self.profiles, self.gammas, self.horizons):
            values.fill(self.variants)

    def close(self) -> None:
        pass
