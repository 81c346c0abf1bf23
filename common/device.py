"""Emulated device: how slow this agent's hardware is, and how that changes over time.

Compute runs at this machine's speed; the device model stretches it. A local iteration that
took ``c`` seconds of compute (thread CPU time, so other processes competing for this machine
do not count as the agent's work) is made to take ``c / speed + steps × step_delay_s`` (the
env-step throttle) by sleeping the difference, unless the virtual clock is on, in which case
the emulated time is only accounted. Speeds above 1 cannot be emulated by sleeping and are
only accounted. Every request and every answer also pays ``latency_s`` of one-way network
latency.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fedhpg.common.config import RunConfig, per_agent


@dataclass(kw_only=True)
class DeviceModel:
    """One agent's device: base speed, throttle, latency and time-varying schedule."""

    speed: float = 1.0
    step_delay_s: float = 0.0
    latency_s: float = 0.0
    schedule: str = "constant"
    period_rounds: int = 10
    amplitude: float = 0.5
    virtual_clock: bool = False
    seed: int = 0
    emulated_s: float = 0.0
    """Emulated seconds accumulated since the last :meth:`take_emulated`."""
    sleep: Callable[[float], None] = time.sleep
    """How waiting is done; the agent process swaps in a sleep its server can interrupt."""
    _walk: float = field(default=1.0, init=False)
    _walk_round: int = field(default=0, init=False)

    def speed_at(self, round_index: int) -> float:
        """The device speed during ``round_index`` (rounds count from 1)."""
        if self.schedule == "constant":
            return self.speed
        if self.schedule == "periodic":
            phase = 2.0 * math.pi * (round_index - 1) / self.period_rounds
            return self.speed * (1.0 + self.amplitude * math.sin(phase))
        if self.schedule == "random_walk":
            return self.speed * self._random_walk(round_index)
        raise ValueError(f"unknown speed schedule {self.schedule!r}")

    def _random_walk(self, round_index: int) -> float:
        """A multiplicative walk in [1 - A, 1 + A], reproducible from (seed, round)."""
        if round_index < self._walk_round:
            self._walk, self._walk_round = 1.0, 0
        while self._walk_round < round_index:
            self._walk_round += 1
            rng = np.random.default_rng([self.seed, self._walk_round])
            step = float(rng.normal(0.0, self.amplitude / 3.0))
            self._walk = min(
                max(self._walk * (1.0 + step), 1.0 - self.amplitude), 1.0 + self.amplitude
            )
        return self._walk

    def spend(self, real_s: float, env_steps: int, round_index: int) -> float:
        """Emulate one local iteration; returns its emulated duration."""
        emulated = real_s / self.speed_at(round_index) + env_steps * self.step_delay_s
        self._wait(emulated - real_s)
        self.emulated_s += emulated
        return emulated

    def transmit(self) -> None:
        """Emulate the one-way latency of a message."""
        if self.latency_s > 0:
            self._wait(self.latency_s)
            self.emulated_s += self.latency_s

    def take_emulated(self) -> float:
        spent, self.emulated_s = self.emulated_s, 0.0
        return spent

    def _wait(self, seconds: float) -> None:
        if seconds > 0 and not self.virtual_clock:
            self.sleep(seconds)


def device_for(run: RunConfig, index: int) -> DeviceModel:
    """Agent ``index``'s device as the run configures it."""
    agents = run.agents
    return DeviceModel(
        speed=float(per_agent(agents.speeds, index)),
        step_delay_s=float(per_agent(agents.step_delays_s, index)),
        latency_s=float(per_agent(agents.latencies_s, index)),
        schedule=agents.schedule,
        period_rounds=agents.schedule_period_rounds,
        amplitude=agents.schedule_amplitude,
        virtual_clock=agents.virtual_clock,
        seed=int(np.random.SeedSequence([run.seed, index]).generate_state(1)[0]),
    )
