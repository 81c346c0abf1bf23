"""Emulated device: how slow this agent's hardware is, and how that changes over time.

Two clocks tell how long a local iteration takes on the emulated device.

``measured`` (the default): compute runs at this machine's speed and the device stretches
it. An iteration that took ``c`` seconds of compute (thread CPU time, so other processes
competing for this machine do not count as the agent's work) takes ``c / speed + steps ×
step_delay_s`` (the env-step throttle). Every message pays ``latency_s`` of one-way latency.
This follows the machine: a loaded or slower machine gives other emulated times.

``counted``: the time is computed from the work counted, never from a measurement, so it is
the same bit for bit on any machine under any load. An iteration that ran ``steps`` env
steps and differentiated ``grad_steps`` trajectory steps through a policy of ``d``
parameters takes ``(steps × step_cost_s + grad_steps × grad_cost_s × d / 1e4) / speed +
steps × step_delay_s``; a message of ``n`` bytes takes ``latency_s + 8n / (bandwidth_mbps ×
1e6)``. The in-process pool and the agent process charge the same two messages per round
(θ̃ down, θ up), of :func:`message_bytes` each, so both runtimes give the same emulated time.

Unless the virtual clock is on, the device sleeps the emulated time minus the compute time
(speeds above 1 cannot be emulated by sleeping and are only accounted); with it on, the
emulated time is only accounted. The sleeping is owed through the round and paid once, by
:meth:`DeviceModel.settle` before the answer leaves, not after each iteration: compute that
follows a sleep can run on cold caches and a clocked-down core, so sleeping between iterations
would charge a slow device for the emulation's own disturbance. The measured clock moves with
the machine's load (on busy cores two equal-work devices of speeds 1 and 0.25 do not measure
exactly 4× apart); the counted clock does not move.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.configuration.vocabularies import CLOCKS
from fedhpg.common.heterogeneity.population import device_value

if TYPE_CHECKING:
    from fedhpg.common.records.round_columns import IterationColumns

GRAD_PARAMS_UNIT = 10_000
"""``grad_cost_s`` is the cost of one trajectory step's backward pass per this many
parameters: the backward pass of a small MLP costs about linearly in its parameters."""

MESSAGE_HEADER_BYTES = 512
"""What the counted clock charges per message on top of θ's float32 bytes: the envelope,
round number and statistics, rounded up (encoded, a Train request carries 71 bytes besides
θ and an Update about 240 plus its algorithm's statistics). A fixed figure rather than the
encoded length so that the in-process pool, which encodes nothing, charges the same bytes."""


def message_bytes(num_params: int) -> int:
    """Bytes the counted clock charges for a message carrying a θ of ``num_params``."""
    return 4 * num_params + MESSAGE_HEADER_BYTES


Number = TypeVar("Number", float, np.ndarray)
"""One device's value (a Python float) or a column of devices' (a float64 array): the prices
below are one formula for both, and IEEE 754 rounds each elementwise operation exactly as the
same operation on one float, so a host's column of agents prices each exactly as its own
device would."""


def _joined(parts: list[np.ndarray]) -> np.ndarray:
    """``parts`` end to end (the one part itself where there is one)."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def compute_seconds(
    counted: bool,
    real_s: Number,
    env_steps: Number,
    grad_steps: Number,
    step_cost_s: Number,
    grad_cost_s: Number,
    num_params: int,
) -> Number:
    """An iteration's compute seconds at speed 1: measured (``real_s``), or priced from the
    counts on the counted clock."""
    if not counted:
        return real_s
    gradient_s = grad_steps * grad_cost_s * num_params / GRAD_PARAMS_UNIT
    return env_steps * step_cost_s + gradient_s


def iteration_seconds(
    compute_s: Number, speed: Number, env_steps: Number, step_delay_s: Number
) -> Number:
    """An iteration's emulated seconds: its compute stretched by the speed, plus the env-step
    throttle."""
    return compute_s / speed + env_steps * step_delay_s


def transfer_seconds(
    counted: bool, latency_s: Number, bandwidth_mbps: Number, num_bytes: int
) -> Number:
    """One-way seconds of a message of ``num_bytes`` (the bytes count on the counted clock,
    through a link of ``bandwidth_mbps``; 0 = unlimited)."""
    if not counted:
        return latency_s
    if isinstance(bandwidth_mbps, np.ndarray):
        # the transfer where the bandwidth is set, 0 where it is unlimited (never divided)
        limited = bandwidth_mbps > 0
        transfer = np.divide(8.0 * num_bytes, bandwidth_mbps * 1e6,
                             out=np.zeros(limited.shape), where=limited)  # fmt: skip
        return latency_s + transfer
    if bandwidth_mbps <= 0:
        return latency_s
    return latency_s + 8.0 * num_bytes / (bandwidth_mbps * 1e6)


@dataclass(kw_only=True)
class DeviceModel:
    """One agent's device: base speed, throttle, latency, costs and time-varying schedule."""

    speed: float = 1.0
    step_delay_s: float = 0.0
    latency_s: float = 0.0
    schedule: str = "constant"
    period_rounds: int = 10
    amplitude: float = 0.5
    virtual_clock: bool = False
    clock: str = "measured"
    """'measured' (compute time as measured here) or 'counted' (from the work counted)."""
    step_cost_s: float = 0.0
    """Counted clock: seconds of one env step (sampling and the policy's forward pass)."""
    grad_cost_s: float = 0.0
    """Counted clock: seconds of one trajectory step's backward pass per 1e4 parameters."""
    bandwidth_mbps: float = 0.0
    """Counted clock: link bandwidth in megabits per second; 0 = unlimited."""
    seed: int = 0
    emulated_s: float = 0.0
    """Emulated seconds accumulated since the last :meth:`take_emulated`."""
    owed_s: float = field(default=0.0, init=False)
    """Seconds of sleep owed since the last :meth:`settle` or :meth:`take_emulated`."""
    sleep: Callable[[float], None] = time.sleep
    """How waiting is done; the agent process swaps in a sleep its server can interrupt."""
    _walk: float = field(default=1.0, init=False)
    _walk_round: int = field(default=0, init=False)

    @property
    def counted(self) -> bool:
        return CLOCKS.get(self.clock).counts_work

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

    def compute_s(
        self, real_s: float, env_steps: int, grad_steps: int = 0, num_params: int = 0
    ) -> float:
        """Compute seconds of an iteration at speed 1 (:func:`compute_seconds`)."""
        return compute_seconds(self.counted, real_s, float(env_steps), float(grad_steps),
                               self.step_cost_s, self.grad_cost_s, num_params)  # fmt: skip

    def spend(
        self,
        real_s: float,
        env_steps: int,
        round_index: int,
        *,
        grad_steps: int = 0,
        num_params: int = 0,
    ) -> float:
        """Emulate one local iteration (its sleep is owed until :meth:`settle`); returns its
        emulated duration.

        ``grad_steps`` and ``num_params`` only matter to the counted clock.
        """
        compute = self.compute_s(real_s, env_steps, grad_steps, num_params)
        emulated = iteration_seconds(
            compute, self.speed_at(round_index), float(env_steps), self.step_delay_s
        )
        self._wait(emulated - real_s)
        self.emulated_s += emulated
        return emulated

    def transfer_s(self, num_bytes: int) -> float:
        """One-way time of a message of ``num_bytes`` (:func:`transfer_seconds`)."""
        return transfer_seconds(self.counted, self.latency_s, self.bandwidth_mbps, num_bytes)

    def transmit(self, num_bytes: int = 0) -> None:
        """Emulate the one-way latency (and, on the counted clock, transfer) of a message
        (owed until :meth:`settle`, like an iteration's sleep)."""
        seconds = self.transfer_s(num_bytes)
        if seconds > 0:
            self._wait(seconds)
            self.emulated_s += seconds

    def settle(self) -> None:
        """Sleep what the round owes (nothing on the virtual clock)."""
        owed, self.owed_s = self.owed_s, 0.0
        if owed > 0:
            self.sleep(owed)

    def take_emulated(self) -> float:
        """The emulated seconds since the last call; what was owed and not settled (a
        cancelled round's) is forgiven."""
        spent, self.emulated_s, self.owed_s = self.emulated_s, 0.0, 0.0
        return spent

    def _wait(self, seconds: float) -> None:
        if seconds > 0 and not self.virtual_clock:
            self.owed_s += seconds


def device_for(run: RunConfig, index: int) -> DeviceModel:
    """Agent ``index``'s device as the run configures it: each field from
    ``agents.population`` where it sets one, else from its ``agents.*`` list."""
    agents = run.agents
    return DeviceModel(
        speed=device_value(run, index, "speed"),
        step_delay_s=device_value(run, index, "step_delay_s"),
        latency_s=device_value(run, index, "latency_s"),
        schedule=agents.schedule,
        period_rounds=agents.schedule_period_rounds,
        amplitude=agents.schedule_amplitude,
        virtual_clock=agents.virtual_clock,
        clock=agents.clock,
        step_cost_s=device_value(run, index, "step_cost_s"),
        grad_cost_s=device_value(run, index, "grad_cost_s"),
        bandwidth_mbps=device_value(run, index, "bandwidth_mbps"),
        seed=int(np.random.SeedSequence([run.seed, index]).generate_state(1)[0]),
    )


class DeviceColumns:
    """The devices of an agent host's agents on the virtual clock, emulated a column at a time.

    :meth:`round` applies the prices :class:`DeviceModel` applies one agent at a time (the
    request's transfer, each iteration's, the answer's transfer, in that order) to float64
    columns: the same functions, so every agent's emulated time is, bit for bit, what its
    own DeviceModel gives in a one-agent process or the in-process pool
    (tests/test_counted_clock.py)."""

    def __init__(self, devices: Sequence[DeviceModel]) -> None:
        if any(not d.virtual_clock for d in devices):
            raise ValueError("column-wise emulation only accounts time: it needs the virtual clock")
        clocks = {d.clock for d in devices}
        if len(clocks) > 1:
            raise ValueError(f"one clock per run, not {sorted(clocks)}")
        self.devices = list(devices)
        self.counted = bool(clocks) and CLOCKS.get(next(iter(clocks))).counts_work
        self.step_delay_s = np.array([d.step_delay_s for d in devices], dtype=np.float64)
        self.latency_s = np.array([d.latency_s for d in devices], dtype=np.float64)
        self.step_cost_s = np.array([d.step_cost_s for d in devices], dtype=np.float64)
        self.grad_cost_s = np.array([d.grad_cost_s for d in devices], dtype=np.float64)
        self.bandwidth_mbps = np.array([d.bandwidth_mbps for d in devices], dtype=np.float64)
        self._transfer: tuple[tuple[bytes, int], np.ndarray] | None = None

    def transfer_s(self, rows: np.ndarray, num_bytes: int) -> np.ndarray:
        """:meth:`DeviceModel.transfer_s` of the devices at ``rows`` (read-only; kept for the
        next round, which asks the same of the same rows while the host's agents repeat)."""
        key = (rows.tobytes(), num_bytes)
        if self._transfer is None or self._transfer[0] != key:
            seconds = np.asarray(
                transfer_seconds(
                    self.counted, self.latency_s[rows], self.bandwidth_mbps[rows], num_bytes
                ),
                dtype=np.float64,
            )
            seconds.flags.writeable = False
            self._transfer = (key, seconds)
        return self._transfer[1]

    def round(
        self,
        rows: np.ndarray,
        round_index: int,
        num_bytes: int,
        iterations: Sequence[IterationColumns],
        num_params: int,
        *,
        messages: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The emulated seconds and the speed of the devices at ``rows`` over one round: a
        message of ``num_bytes`` each way (``messages``; none where the server is in the
        same process) around ``iterations`` (their ``positions`` index ``rows``)."""
        speeds = np.array([self.devices[r].speed_at(round_index) for r in rows.tolist()])
        delay = self.step_delay_s[rows]
        step_cost, grad_cost = self.step_cost_s[rows], self.grad_cost_s[rows]
        message = self.transfer_s(rows, num_bytes) if messages else np.zeros(len(rows))
        emulated = np.zeros(len(rows), dtype=np.float64)
        emulated += message
        if iterations:  # every iteration priced at once, added to its row in the order run
            at = _joined([ran.positions for ran in iterations])
            steps = _joined([ran.env_steps for ran in iterations]).astype(np.float64)
            compute = compute_seconds(
                self.counted,
                _joined([ran.compute_s for ran in iterations]),
                steps,
                _joined([ran.grad_steps for ran in iterations]).astype(np.float64),
                step_cost[at],
                grad_cost[at],
                num_params,
            )
            np.add.at(emulated, at, iteration_seconds(compute, speeds[at], steps, delay[at]))
        emulated += message
        return emulated, speeds
