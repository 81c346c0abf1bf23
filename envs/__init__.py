"""Environments: the paper's GridWorld and heterogeneous gymnasium families."""

from fedhpg.envs.gridworld import register_envs

register_envs()
