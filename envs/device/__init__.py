"""Environment copies that live in torch tensors on the engine's device.

A family with a torch implementation steps every copy of every agent's variant as elementwise
tensor arithmetic, each copy's constants (masses, lengths, gravity, slip, its grid's tables) in
tensors of their own, so a whole federation's environments live on a GPU beside its policies.

- :func:`device_family` turns the variants of one engine into a :class:`DeviceFamily`: their
  constants as a table on the device, built once; it hands out :class:`DeviceCopies` of any of
  them (``copies(rows, counts)``) without touching the host again. None where the family has
  no torch implementation (those step through gymnasium on the CPU:
  ``fedhpg.common.learning.engine.copies``).
- CartPole, Acrobot, Pendulum, MountainCar and GridWorld are built in, one module each, listed
  in :mod:`fedhpg.envs.device.registry`; each is checked step for step against its gymnasium
  environment (``tests/test_device_envs.py``). A plugin adds one with
  :func:`register_device_family`.

Randomness comes from the caller: :class:`ResetStream` hands each copy's reset its own
uniforms, and a family whose steps are random (GridWorld's slip) asks for ``step_noise``
uniforms per copy and step, so an environment never owns a generator and a copy's episode
depends on its own stream alone.
"""

from fedhpg.envs.device.protocols import (
    CopyStep,
    DeviceCopies,
    DeviceFamily,
    Implementation,
    ResetStream,
)
from fedhpg.envs.device.registry import device_copies, device_family, register_device_family

__all__ = [
    "CopyStep",
    "DeviceCopies",
    "DeviceFamily",
    "Implementation",
    "ResetStream",
    "device_copies",
    "device_family",
    "register_device_family",
]
