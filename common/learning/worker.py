"""What every placement of an agent shares: its policy built from the run seed, θ̃_0, and the
work record of one local iteration that the device emulation prices."""

from __future__ import annotations

import gymnasium as gym
import torch

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.learning.policies import Policy, get_flat_params, make_policy
from fedhpg.envs.base import EnvVariant


def build_policy(variant: EnvVariant, run: RunConfig) -> Policy:
    """The run's policy for the variant's spaces, initialised from the run seed alone."""
    return policy_and_spaces(variant, run)[0]


def policy_and_spaces(variant: EnvVariant, run: RunConfig) -> tuple[Policy, gym.Space, gym.Space]:
    """:func:`build_policy` and the variant's observation and action spaces, from one
    environment."""
    env = variant.make_env()
    # Only the CPU generator, saved and restored by hand: torch.random.fork_rng() and
    # torch.manual_seed() also reach for every CUDA device, which initialises CUDA where torch
    # has it, and CUDA then refuses every process forked afterwards (fedhpg-run calls this
    # before it forks the server and the agents, and each of them calls it again).
    state = torch.default_generator.get_state()
    try:
        torch.default_generator.manual_seed(run.seed)
        policy = make_policy(env.observation_space, env.action_space, run.policy)
        return policy, env.observation_space, env.action_space
    finally:
        torch.default_generator.set_state(state)
        env.close()


def initial_theta(variant: EnvVariant, run: RunConfig) -> torch.Tensor:
    """θ̃_0, the server's starting point: deterministic in the run seed."""
    return get_flat_params(build_policy(variant, run))
