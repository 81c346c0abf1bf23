"""Heterogeneous families of gymnasium tasks: K variants from (seed, K, level).

Every family draws, per agent k and parameter p, a number u_{k,p} uniform in [−1, 1] from the
seed, and sets p = default · (1 + spread_p · level · u_{k,p}) (or default + spread · level · u
for the CartPole pole length). Level 0 gives K copies of the stock task; level 1 the widest
spread below. Observation and action spaces never change.

| family | parameters (spread at level 1) |
|---|---|
| cartpole | pole half-length 0.5 ± 0.4 (0.1–0.9), pole and cart mass ±50%, force ±30%, g ±20% |
| acrobot | both link lengths ±40%, both link masses ±40% |
| pendulum | g ±30%, mass ±40%, length ±40%; action cost 0–0.01·level |
| mountaincar | engine force ±30%, gravity ±20% |
| lunarlander | gravity −10 ± 1.5 (in [−12, 0)), wind power 0–15, turbulence 0–1.5 |
| lunarlander-continuous | as lunarlander; action cost 0–0.1·level |
| halfcheetah | gravity ±30%, friction ±50%, body masses ±30%; action cost 0.1 × (1 ± 0.5·level·u) |

Each variant also gets its own discount γ_k = gamma − 0.01·level·|u| unless the run fixes one.

The u of all K agents form one K×count matrix drawn row-major from one stream, so agent k's
row does not depend on K; :func:`_rows` draws the rows asked for alone, and each family is a
:class:`~fedhpg.envs.lazy.LazyFamily` (agent 9 999 of 10 000 costs what agent 0 does).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fedhpg.envs.base import EnvVariant
from fedhpg.envs.gym_variant import GymVariant
from fedhpg.envs.lazy import LazyFamily
from fedhpg.envs.mujoco_assets import without_settotalmass

FamilyFactory = LazyFamily

SPAN_GAP = 4096
"""Rows asked for that lie closer than this are drawn in one span with the rows between them
(cheaper than a new generator); farther apart, the next span skips ahead."""


def _rows(seed: int, tag: int, indices: Sequence[int], count: int) -> np.ndarray:
    """Rows ``indices`` of u = ``default_rng([seed, tag]).uniform(−1, 1, size=(K, count))``,
    u in [−1, 1] reproducible from (seed, family), without drawing the rows before them: a
    uniform double takes one 64-bit output of PCG64, filled row-major, so row k starts at
    output k·count and the bit generator's ``advance`` jumps there in O(log k)."""
    wanted = np.asarray(indices, dtype=np.int64).reshape(-1)
    out = np.empty((wanted.size, count))
    if wanted.size == 0:
        return out
    order = np.argsort(wanted, kind="stable")
    ascending = wanted[order]
    spans = np.split(order, np.flatnonzero(np.diff(ascending) > SPAN_GAP) + 1)
    for span in spans:
        first, last = int(wanted[span].min()), int(wanted[span].max())
        bits = np.random.PCG64([seed, tag])
        bits.advance(first * count)
        drawn = np.random.Generator(bits).uniform(-1.0, 1.0, size=(last - first + 1, count))
        out[span] = drawn[wanted[span] - first]
    return out


def _gamma(gamma: float, level: float, u: float) -> float:
    return round(gamma - 0.01 * level * abs(float(u)), 6)


def _reject_options(family: str, options: dict[str, Any]) -> None:
    if options:
        raise ValueError(f"env family {family!r} does not support the options {sorted(options)}")


CARTPOLE_REPORTED = ("length", "masspole", "masscart", "force_mag", "gravity")


def _cartpole_at(
    indices: Sequence[int],
    /,
    *,
    seed: int,
    num_agents: int,
    level: float,
    gamma: float = 0.99,
    **options: Any,
) -> list[EnvVariant]:
    _reject_options("cartpole", options)
    u = _rows(seed, 0xCA27, indices, 6)
    variants: list[EnvVariant] = []
    for k, row in zip(indices, u, strict=True):
        length = 0.5 + 0.4 * level * row[0]
        masspole = 0.1 * (1 + 0.5 * level * row[1])
        masscart = 1.0 * (1 + 0.5 * level * row[2])
        physics = {
            "length": float(length),
            "masspole": float(masspole),
            "masscart": float(masscart),
            "total_mass": float(masspole + masscart),
            "polemass_length": float(masspole * length),
            "force_mag": float(10.0 * (1 + 0.3 * level * row[3])),
            "gravity": float(9.8 * (1 + 0.2 * level * row[4])),
        }
        variants.append(
            GymVariant(
                family="cartpole",
                index=int(k),
                gamma=_gamma(gamma, level, row[5]),
                params={key: round(v, 4) for key, v in physics.items() if key in CARTPOLE_REPORTED},
                env_id="CartPole-v1",
                attributes=physics,
            )
        )
    return variants


def _acrobot_at(
    indices: Sequence[int],
    /,
    *,
    seed: int,
    num_agents: int,
    level: float,
    gamma: float = 0.99,
    **options: Any,
) -> list[EnvVariant]:
    _reject_options("acrobot", options)
    u = _rows(seed, 0xAC20, indices, 5)
    names = ("LINK_LENGTH_1", "LINK_LENGTH_2", "LINK_MASS_1", "LINK_MASS_2")
    variants: list[EnvVariant] = []
    for k, row in zip(indices, u, strict=True):
        physics = {name: float(1.0 * (1 + 0.4 * level * row[i])) for i, name in enumerate(names)}
        # The centre of mass sits mid-link; keep it there when the length changes.
        physics["LINK_COM_POS_1"] = physics["LINK_LENGTH_1"] / 2
        physics["LINK_COM_POS_2"] = physics["LINK_LENGTH_2"] / 2
        variants.append(
            GymVariant(
                family="acrobot",
                index=int(k),
                gamma=_gamma(gamma, level, row[4]),
                params={n.lower(): round(physics[n], 4) for n in names},
                env_id="Acrobot-v1",
                attributes=physics,
            )
        )
    return variants


def _pendulum_at(
    indices: Sequence[int],
    /,
    *,
    seed: int,
    num_agents: int,
    level: float,
    gamma: float = 0.99,
    **options: Any,
) -> list[EnvVariant]:
    _reject_options("pendulum", options)
    u = _rows(seed, 0x9E4D, indices, 5)
    variants: list[EnvVariant] = []
    for k, row in zip(indices, u, strict=True):
        physics = {
            "g": float(10.0 * (1 + 0.3 * level * row[0])),
            "m": float(1.0 * (1 + 0.4 * level * row[1])),
            "l": float(1.0 * (1 + 0.4 * level * row[2])),
        }
        cost = 0.01 * level * (1 + row[3]) / 2
        variants.append(
            GymVariant(
                family="pendulum",
                index=int(k),
                gamma=_gamma(gamma, level, row[4]),
                params={
                    **{key: round(v, 4) for key, v in physics.items()},
                    "action_cost": round(cost, 5),
                },
                env_id="Pendulum-v1",
                attributes=physics,
                action_cost=float(cost),
            )
        )
    return variants


def _mountaincar_at(
    indices: Sequence[int],
    /,
    *,
    seed: int,
    num_agents: int,
    level: float,
    gamma: float = 0.99,
    **options: Any,
) -> list[EnvVariant]:
    _reject_options("mountaincar", options)
    u = _rows(seed, 0x3C4A, indices, 3)
    variants: list[EnvVariant] = []
    for k, row in zip(indices, u, strict=True):
        physics = {
            "force": float(0.001 * (1 + 0.3 * level * row[0])),
            "gravity": float(0.0025 * (1 + 0.2 * level * row[1])),
        }
        variants.append(
            GymVariant(
                family="mountaincar",
                index=int(k),
                gamma=_gamma(gamma, level, row[2]),
                params={key: round(v, 7) for key, v in physics.items()},
                env_id="MountainCar-v0",
                attributes=physics,
            )
        )
    return variants


def _lunarlander_at(
    continuous: bool,
    indices: Sequence[int],
    *,
    seed: int,
    num_agents: int,
    level: float,
    gamma: float = 0.99,
    **options: Any,
) -> list[EnvVariant]:
    family = "lunarlander-continuous" if continuous else "lunarlander"
    _reject_options(family, options)
    u = _rows(seed, 0x1A4D, indices, 5)
    variants: list[EnvVariant] = []
    for k, row in zip(indices, u, strict=True):
        wind = 15.0 * level * (1 + row[1]) / 2
        kwargs = {
            "continuous": continuous,
            "gravity": float(np.clip(-10.0 + 1.5 * level * row[0], -11.99, -0.01)),
            "enable_wind": bool(wind > 0.0),
            "wind_power": float(wind),
            "turbulence_power": float(1.5 * level * (1 + row[2]) / 2),
        }
        cost = 0.1 * level * (1 + row[3]) / 2 if continuous else 0.0
        params = {key: round(v, 4) for key, v in kwargs.items() if isinstance(v, float)}
        if continuous:
            params["action_cost"] = round(float(cost), 5)
        variants.append(
            GymVariant(
                family=family,
                index=int(k),
                gamma=_gamma(gamma, level, row[4]),
                params=params,
                env_id="LunarLander-v3",
                env_kwargs=kwargs,
                action_cost=float(cost),
            )
        )
    return variants


def _discrete_lander_at(indices: Sequence[int], /, **kwargs: Any) -> list[EnvVariant]:
    return _lunarlander_at(False, indices, **kwargs)


def _continuous_lander_at(indices: Sequence[int], /, **kwargs: Any) -> list[EnvVariant]:
    return _lunarlander_at(True, indices, **kwargs)


def _halfcheetah_at(
    indices: Sequence[int],
    /,
    *,
    seed: int,
    num_agents: int,
    level: float,
    gamma: float = 0.99,
    **options: Any,
) -> list[EnvVariant]:
    _reject_options("halfcheetah", options)
    xml_file, total_mass = without_settotalmass("half_cheetah.xml")
    u = _rows(seed, 0x4C, indices, 5)
    variants: list[EnvVariant] = []
    for k, row in zip(indices, u, strict=True):
        scales = {
            "gravity": float(1 + 0.3 * level * row[0]),
            "friction": float(1 + 0.5 * level * row[1]),
            "mass": float(1 + 0.3 * level * row[2]),
        }
        cost = 0.1 * (1 + 0.5 * level * row[3])
        variants.append(
            GymVariant(
                family="halfcheetah",
                index=int(k),
                gamma=_gamma(gamma, level, row[4]),
                params={
                    **{f"{n}_scale": round(v, 4) for n, v in scales.items()},
                    "ctrl_cost_weight": round(cost, 4),
                },
                env_id="HalfCheetah-v5",
                env_kwargs={"ctrl_cost_weight": float(cost), "xml_file": xml_file},
                mujoco_scales=scales,
                mujoco_total_mass=total_mass,
            )
        )
    return variants


cartpole = LazyFamily(_cartpole_at)
acrobot = LazyFamily(_acrobot_at)
pendulum = LazyFamily(_pendulum_at)
mountaincar = LazyFamily(_mountaincar_at)
lunarlander = LazyFamily(_discrete_lander_at)
lunarlander_continuous = LazyFamily(_continuous_lander_at)
halfcheetah = LazyFamily(_halfcheetah_at)

GYM_FAMILIES: dict[str, FamilyFactory] = {
    "cartpole": cartpole,
    "acrobot": acrobot,
    "pendulum": pendulum,
    "mountaincar": mountaincar,
    "lunarlander": lunarlander,
    "lunarlander-continuous": lunarlander_continuous,
    "halfcheetah": halfcheetah,
}
