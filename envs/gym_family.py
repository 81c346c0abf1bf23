"""Any registered gymnasium environment as a heterogeneous family: ``env=gym env.id=ID``.

Every agent runs the same gymnasium id; what differs between agents is declared in the
config, name by name, as a seeded distribution (:mod:`fedhpg.envs.distributions`) or a
spread around the environment's own value::

    env:
      family: gym
      id: MountainCar-v0
      kwargs: {}                                   # constructor keywords, every agent's
      vary:
        force: {spread: 0.5}                       # 0.001 · (1 + 0.5 · level · u), u ~ U(−1, 1)
        gravity: {uniform: {low: 0.002, high: 0.003}}
        gamma: {choice: [0.99, 0.999]}             # the agent's discount γ_k

A name the environment's constructor takes (``FrozenLake-v1``'s ``success_rate``) is passed
to ``gym.make``; any other must be an attribute of the unwrapped environment
(``MountainCar-v0``'s ``force`` and ``gravity``, ``Acrobot-v1``'s ``LINK_MASS_1``), set after it
is built; ``gamma`` is the agent's discount. Agent k's values are drawn from a generator seeded
by (seed, k, name) alone: the same on every host, whatever K. ``env.level`` scales the
``spread`` entries (0: every agent the stock environment); the other distributions are drawn
as written. An environment that needs code rather than numbers (a model file, a wrapper, a
reward of its own) is a family of its own: see the guide's "Environments" page.
"""

from __future__ import annotations

import functools
import inspect
import json
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator

from fedhpg.envs import distributions
from fedhpg.envs.base import EnvVariant
from fedhpg.envs.gym_variant import GymVariant
from fedhpg.envs.lazy import LazyFamily

SPREAD = "spread"
"""``{spread: s}``: the environment's own value × (1 + s · level · u), u ~ U(−1, 1)."""
_STREAM_TAG = 0x67A1
DISCOUNT = "gamma"


class VariationError(ValueError):
    """A gym family setting that cannot work; ``key`` names it (``env.id``, ``env.vary.x``)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def _check_spec(name: str, spec: Any) -> None:
    key = f"env.vary.{name}"
    if isinstance(spec, Mapping) and SPREAD in spec:
        spread = spec[SPREAD]
        if set(spec) != {SPREAD} or not isinstance(spread, int | float) or spread < 0:
            raise VariationError(key, f"got {dict(spec)!r}, a spread is {{spread: s}}, s >= 0")
        return
    try:
        distributions.check(spec, numbers_only=False)
    except distributions.DistributionError as error:
        raise VariationError(f"{key}{error.where}", f"{error} (or {{spread: s}})") from None


@functools.lru_cache(maxsize=16)
def _creator(env_id: str) -> tuple[Any, Any]:
    try:
        spec = gym.spec(env_id)
    except gym.error.Error as error:
        raise VariationError("env.id", f"{env_id!r}: {error}") from None
    entry = spec.entry_point
    try:
        creator = load_env_creator(entry) if isinstance(entry, str) else entry
    except (ImportError, AttributeError, gym.error.Error) as error:
        raise VariationError("env.id", f"{env_id!r} cannot be built here: {error}") from None
    return spec, creator


@functools.lru_cache(maxsize=16)
def _probe(env_id: str, kwargs_json: str) -> gym.Env:
    """One environment of ``env_id``, built once, to read attribute names and values from."""
    return gym.make(env_id, **json.loads(kwargs_json)).unwrapped


@functools.lru_cache(maxsize=64)
def _knobs(env_id: str, names: tuple[str, ...], kwargs_json: str) -> dict[str, tuple[str, Any]]:
    """How each varied name reaches the environment: ("kwarg" | "attribute", its stock
    value, or None where it has none)."""
    spec, creator = _creator(env_id)
    try:
        parameters = inspect.signature(creator).parameters
    except (TypeError, ValueError):
        parameters = {}  # type: ignore[assignment]
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())
    stock = {**spec.kwargs, **json.loads(kwargs_json)}
    knobs: dict[str, tuple[str, Any]] = {}
    for name in names:
        if name == DISCOUNT:
            continue
        parameter = parameters.get(name)
        if parameter is not None and parameter.kind is not inspect.Parameter.VAR_KEYWORD:
            default = stock.get(name, parameter.default)
            knobs[name] = ("kwarg", None if default is inspect.Parameter.empty else default)
            continue
        env = _probe(env_id, kwargs_json)
        if hasattr(env, name) and not callable(getattr(env, name)):
            knobs[name] = ("attribute", getattr(env, name))
        elif takes_any:
            knobs[name] = ("kwarg", stock.get(name))
        else:
            keywords = sorted(n for n in parameters if n not in ("render_mode", "kwargs"))
            attributes = sorted(
                n
                for n, v in vars(env).items()
                if not n.startswith("_") and isinstance(v, int | float | bool)
            )
            raise VariationError(
                f"env.vary.{name}",
                f"{env_id} has no constructor keyword or attribute {name!r} (keywords: "
                f"{', '.join(keywords) or 'none'}; attributes: {', '.join(attributes[:12])})",
            )
    return knobs


def _value(
    spec: Mapping[str, Any], stock: Any, name: str, *, seed: int, index: int, level: float
) -> Any:
    sequence = np.random.SeedSequence([seed, _STREAM_TAG, index, zlib.crc32(name.encode())])
    rng = np.random.default_rng(sequence)
    if SPREAD in spec:
        if not isinstance(stock, int | float) or isinstance(stock, bool):
            raise VariationError(
                f"env.vary.{name}",
                f"a spread needs the environment's own number, and {name} is {stock!r}: give "
                "a distribution",
            )
        value = float(stock) * (1.0 + float(spec[SPREAD]) * level * rng.uniform(-1.0, 1.0))
        return type(stock)(value) if isinstance(stock, int) else value
    return distributions.sample(spec, rng)


def _shown(value: Any) -> Any:
    return round(value, 6) if isinstance(value, float) else value


def gym_variants_at(
    indices: Sequence[int],
    /,
    *,
    seed: int,
    num_agents: int,
    level: float,
    id: str | None = None,
    kwargs: Mapping[str, Any] | None = None,
    vary: Mapping[str, Any] | None = None,
    gamma: float = 0.99,
    max_episode_steps: int = 0,
    **options: Any,
) -> list[EnvVariant]:
    """The variants of agents ``indices``: ``id`` with ``kwargs``, and each name of ``vary``
    drawn for the agent (see the module's docstring); episodes end after ``max_episode_steps``
    (``env.horizon``; default: the id's registered limit)."""
    if options:
        raise VariationError("env.options", f"env=gym takes no options {sorted(options)}")
    if not id:
        raise VariationError(
            "env.id", "env=gym needs a registered gymnasium id, e.g. env.id=MountainCar-v0"
        )
    fixed = dict(kwargs or {})
    declared = dict(vary or {})
    for name, spec in declared.items():
        _check_spec(name, spec)
    kwargs_json = json.dumps(fixed, sort_keys=True)
    spec, _ = _creator(id)  # a registered id, even with nothing varied
    if not max_episode_steps and spec.max_episode_steps is None:
        raise VariationError("env.horizon", f"{id} has no step limit: set env.horizon=<steps>")
    knobs = _knobs(id, tuple(sorted(declared)), kwargs_json)
    variants: list[EnvVariant] = []
    for k in indices:
        drawn = {
            name: _value(
                declared[name],
                gamma if name == DISCOUNT else knobs[name][1],
                name,
                seed=seed,
                index=int(k),
                level=level,
            )
            for name in sorted(declared)
        }
        discount = float(drawn.pop(DISCOUNT, gamma))
        if not 0.0 < discount <= 1.0:
            raise VariationError(f"env.vary.{DISCOUNT}", f"drew γ = {discount:g}, not in (0, 1]")
        variants.append(
            GymVariant(
                family="gym",
                index=int(k),
                gamma=round(discount, 6),
                params={name: _shown(value) for name, value in drawn.items()},
                env_id=id,
                env_kwargs={
                    **fixed,
                    **{n: v for n, v in drawn.items() if knobs[n][0] == "kwarg"},
                },
                attributes={n: v for n, v in drawn.items() if knobs[n][0] == "attribute"},
                step_limit=int(max_episode_steps),
            )
        )
    return variants


gym_family = LazyFamily(gym_variants_at)
