"""What every placement of an agent shares: its policy built from the run seed, θ̃_0, the
per-(seed, agent, round) numpy streams the compiled engine reproduces, and the work record of
one local iteration that the device emulation prices."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import torch

from fedhpg.common.config import RunConfig
from fedhpg.common.policies import Policy, get_flat_params, make_policy
from fedhpg.envs.base import EnvVariant


class Stream(IntEnum):
    """Purposes of the per-(seed, agent, round) random streams."""

    TRAIN = 0
    EVALUATE = 1
    ATTACK = 2


def random_stream(
    seed: int, agent_index: int, round_index: int, purpose: Stream
) -> np.random.Generator:
    """A stream that depends only on (seed, agent, round, purpose).

    A restarted agent, or the same agent in another process, redoes exactly the same work.
    """
    return np.random.default_rng([seed, agent_index, round_index, int(purpose)])


def build_policy(variant: EnvVariant, run: RunConfig) -> Policy:
    """The run's policy for the variant's spaces, initialised from the run seed alone."""
    env = variant.make_env()
    # Only the CPU generator, saved and restored by hand: torch.random.fork_rng() and
    # torch.manual_seed() also reach for every CUDA device, which initialises CUDA where torch
    # has it, and CUDA then refuses every process forked afterwards (fedhpg-run calls this
    # before it forks the server and the agents, and each of them calls it again).
    state = torch.default_generator.get_state()
    try:
        torch.default_generator.manual_seed(run.seed)
        return make_policy(env.observation_space, env.action_space, run.policy)
    finally:
        torch.default_generator.set_state(state)
        env.close()


def initial_theta(variant: EnvVariant, run: RunConfig) -> torch.Tensor:
    """θ̃_0, the server's starting point: deterministic in the run seed."""
    return get_flat_params(build_policy(variant, run))


@dataclass(frozen=True)
class IterationWork:
    """The work of one local iteration, as the device emulation prices it."""

    iteration: int
    compute_s: float
    """Thread CPU time the iteration took here (what the measured clock stretches)."""
    env_steps: int
    grad_steps: int
    """Trajectory steps differentiated (a VR step differentiates its mini-batch twice)."""
