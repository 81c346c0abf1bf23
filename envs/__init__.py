"""Environments: the paper's GridWorld and heterogeneous gymnasium families.

Importing the package registers ``fedhpg/GridWorld-v0`` and every family's variant id
(``fedhpg/CartPole-v1``, ...: :mod:`fedhpg.envs.gym_ids`) with gymnasium.
"""

from fedhpg.envs.gridworld import register_envs
from fedhpg.envs.gym_ids import register_gym_ids

register_envs()
register_gym_ids()
