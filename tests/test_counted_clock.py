"""The counted clock: emulated time priced from counted work, the same on any machine.

Runs are compared exactly (``==`` on every float): the counted clock must not depend on how
long anything took here, so there is no tolerance to give.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from procs import processes, start

from fedhpg.common.configuration.config import RunConfig, validate
from fedhpg.common.configuration.config_error import ConfigError
from fedhpg.common.heterogeneity.device import (
    GRAD_PARAMS_UNIT,
    DeviceColumns,
    DeviceModel,
    message_bytes,
)
from fedhpg.common.heterogeneity.variants import run_variants
from fedhpg.common.learning.group import make_agent_group
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.records.round_columns import IterationColumns
from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord

STEP_S, GRAD_S, LATENCY_S, BANDWIDTH_MBPS = 2e-5, 3e-5, 0.004, 50.0


def _overrides(algo: str = "fedhpg", clock: str = "counted") -> list[str]:
    return [
        "rounds=3",
        "seed=5",
        "env.family=cartpole",
        "env.level=0.5",
        f"algo.name={algo}",
        "agents.num_agents=2",
        "agents.budget.batch_size=[4,6]",
        "agents.budget.local_iters=[2,1]",
        "++agents.budget.inner_steps=[2]",
        "++agents.budget.mini_batch_size=[2]",
        "agents.speeds=[1.0,0.5]",
        "agents.step_delays_s=[0]",
        f"agents.latencies_s=[{LATENCY_S}]",
        f"agents.clock={clock}",
        f"agents.step_costs_s=[{STEP_S}]",
        f"agents.grad_costs_s=[{GRAD_S}]",
        f"agents.bandwidths_mbps=[{BANDWIDTH_MBPS}]",
        "eval.every=3",
        "eval.episodes=2",
    ]


def _in_process(run: RunConfig) -> tuple[torch.Tensor, list[RoundRecord]]:
    records: list[RoundRecord] = []
    theta = run_in_process(run, on_round=[lambda record, _: records.append(record)])
    return theta, records


def _emulated(records: list[RoundRecord]) -> list[list[float]]:
    return [list(r.result.stats.emulated_s) for r in records]


@contextmanager
def _cpu_hog() -> Iterator[subprocess.Popen]:
    """A busy loop beside the test (bounded at 60 s in case the test is killed)."""
    hog = subprocess.Popen(
        [sys.executable, "-c", "import time\nend = time.time() + 60\nwhile time.time() < end: pass"]
    )
    try:
        time.sleep(0.2)  # let it get going
        yield hog
    finally:
        hog.kill()
        hog.wait(timeout=10)


def test_counted_time_is_the_priced_work_not_the_measurement() -> None:
    device = DeviceModel(
        speed=0.5, clock="counted", step_cost_s=STEP_S, grad_cost_s=GRAD_S, virtual_clock=True
    )
    first = device.spend(0.9, 100, 1, grad_steps=100, num_params=5000)
    again = device.spend(0.001, 100, 1, grad_steps=100, num_params=5000)
    assert first == again, "the measured seconds do not count"
    compute = 100 * STEP_S + 100 * GRAD_S * 5000 / GRAD_PARAMS_UNIT
    assert first == compute / 0.5


def test_half_speed_doubles_the_compute_part_exactly() -> None:
    def priced(speed: float, step_delay_s: float = 0.0) -> float:
        device = DeviceModel(
            speed=speed,
            clock="counted",
            step_cost_s=STEP_S,
            grad_cost_s=GRAD_S,
            step_delay_s=step_delay_s,
            virtual_clock=True,
        )
        return device.spend(0.0, 777, 1, grad_steps=1234, num_params=4610)

    assert priced(0.5) == 2 * priced(1.0)
    assert priced(0.25) == 4 * priced(1.0)
    # The env-step throttle is a fixed cost per step, not stretched by the speed.
    assert priced(0.5, 1e-3) == pytest.approx(2 * priced(1.0) + 777 * 1e-3, rel=1e-12)


def test_transfer_time_follows_bytes_and_bandwidth() -> None:
    def transfer(bandwidth: float, num_bytes: int) -> float:
        device = DeviceModel(
            clock="counted", latency_s=LATENCY_S, bandwidth_mbps=bandwidth, virtual_clock=True
        )
        device.transmit(num_bytes)
        return device.take_emulated() - LATENCY_S

    assert transfer(8.0, 1_000_000) == pytest.approx(1.0, rel=1e-12), "8 Mbit at 8 Mbit/s"
    assert transfer(16.0, 1_000_000) == transfer(8.0, 1_000_000) / 2
    assert transfer(8.0, 2_000_000) == 2 * transfer(8.0, 1_000_000)
    assert transfer(0.0, 10**9) == 0.0, "0 = unlimited: latency only"
    measured = DeviceModel(latency_s=LATENCY_S, bandwidth_mbps=8.0, virtual_clock=True)
    measured.transmit(10**6)
    assert measured.take_emulated() == LATENCY_S, "the measured clock charges latency only"
    assert message_bytes(4610) == 4 * 4610 + 512


@pytest.mark.parametrize(("algo", "gradients_per_step"), [("fedhpg", 1), ("fedhpgvr", 2)])
def test_gradient_steps_are_counted_per_iteration(algo: str, gradients_per_step: int) -> None:
    """FedHPG differentiates each batch once; a FedHPGVR step differentiates its mini-batch at
    θ and at the snapshot (its iteration 0, the snapshot's large batch, once)."""
    run = compose(_overrides(algo))
    group = make_agent_group(run, [0])
    try:
        theta = initial_theta(run_variants(run)[0], run)
        work = group.train(1, theta, [0]).iterations
    finally:
        group.close()
    assert len(work) >= 2 and all(w.env_steps.tolist() == [w.env_steps[0]] for w in work)
    assert all(w.env_steps[0] > 0 for w in work)
    for n, w in enumerate(work):
        per_step = 1 if (algo == "fedhpgvr" and n == 0) else gradients_per_step
        assert w.grad_steps[0] == per_step * w.env_steps[0], (algo, n)


def test_emulated_times_identical_across_runs_and_under_load() -> None:
    run = compose(_overrides())
    theta, plain = _in_process(run)
    with _cpu_hog() as hog:
        loaded_theta, loaded = _in_process(compose(_overrides()))
        assert hog.poll() is None, "the hog ran for the whole loaded run"
    assert torch.equal(theta, loaded_theta)
    assert _emulated(plain) == _emulated(loaded), "bit for bit, idle or loaded"
    assert [max(r) for r in _emulated(plain)] == [max(r) for r in _emulated(loaded)]
    # What the emulated time is: the priced work plus two messages (fedhpg differentiates every
    # step once), to rounding; and θ̃ does not depend on the clock.
    num_params = (4 * 64 + 64) + (64 * 64 + 64) + (64 * 2 + 2)  # the 4-64-64-2 MLP
    messages = 2 * (LATENCY_S + 8 * message_bytes(num_params) / (BANDWIDTH_MBPS * 1e6))
    for record in plain:
        for stats, speed in zip(record.result.stats, (1.0, 0.5), strict=True):
            steps = stats.env_steps
            compute = steps * STEP_S + steps * GRAD_S * num_params / GRAD_PARAMS_UNIT
            assert stats.emulated_s == pytest.approx(compute / speed + messages, rel=1e-12)
    measured_theta, _ = _in_process(compose(_overrides(clock="measured")))
    assert torch.equal(theta, measured_theta), "the clock changes no θ"


def test_distributed_emulated_time_equals_in_process_bit_for_bit(tmp_path: Path) -> None:
    """Agent processes that really sleep (virtual_clock off) report the same counted times."""
    overrides = [*_overrides(), "agents.virtual_clock=false"]
    out_dir = tmp_path / "run"
    with processes() as started:
        launcher = start(
            started,
            "fedhpg-run",
            [*overrides, f"server.out_dir={out_dir}", f"hydra.run.dir={tmp_path / 'hydra'}"],
            cwd=tmp_path,
        )
        _, stderr = launcher.communicate(timeout=120)
    assert launcher.returncode == 0, stderr[-3000:]
    lines = (out_dir / "metrics.jsonl").read_text().splitlines()
    distributed = [[a["emulated_s"] for a in json.loads(line)["agents"]] for line in lines]
    _, in_process = _in_process(compose(overrides))
    assert distributed == _emulated(in_process)


def test_unknown_clock_is_named() -> None:
    with pytest.raises(ConfigError, match=r"agents\.clock"):
        validate(compose(["agents.clock=wall"]))
    with pytest.raises(ConfigError, match=r"agents\.bandwidths_mbps\[0\]"):
        validate(compose(["agents.bandwidths_mbps=[-1]"]))


@pytest.mark.parametrize("clock", ["counted", "measured"])
@pytest.mark.parametrize("schedule", ["constant", "periodic", "random_walk"])
def test_column_wise_emulation_is_each_devices_own_to_the_bit(clock: str, schedule: str) -> None:
    """An agent host prices its agents' iterations a column at a time (DeviceColumns); each
    agent's emulated time and speed must be what its own DeviceModel gives, transmit, spend
    per iteration, transmit, exactly (the rounding of each operation is the same only if the
    operations and their order are)."""
    rng = np.random.default_rng(11)
    count, num_params, num_bytes = 300, 4_738, message_bytes(4_738)

    def device(k: int) -> DeviceModel:
        return DeviceModel(
            speed=float(rng.lognormal(0.0, 0.5)),
            step_delay_s=float(rng.uniform(0, 4e-4)) if k % 3 else 0.0,
            latency_s=float(rng.uniform(0, 0.01)) if k % 4 else 0.0,
            schedule=schedule,
            amplitude=0.4,
            virtual_clock=True,
            clock=clock,
            step_cost_s=float(rng.uniform(1e-6, 3e-5)),
            grad_cost_s=float(rng.uniform(1e-6, 3e-5)),
            bandwidth_mbps=float(rng.choice([0.0, rng.uniform(1, 100)])),
            seed=k,
        )

    own = [device(k) for k in range(count)]
    columns = DeviceColumns([replace(d) for d in own])
    for round_index in (1, 2, 7):
        rows = np.sort(rng.choice(count, size=200, replace=False))
        iterations = []
        for _ in range(3):  # each iteration run by a shrinking subset, as τ_k differ
            at = np.flatnonzero(rng.random(len(rows)) < 0.7)
            steps = rng.integers(1, 5_000, size=len(at))
            iterations.append(IterationColumns(at, rng.uniform(0, 0.05, len(at)), steps, 2 * steps))
        emulated, speeds = columns.round(rows, round_index, num_bytes, iterations, num_params)
        expected = []
        for position, r in enumerate(rows.tolist()):
            d = own[r]
            d.take_emulated()
            d.transmit(num_bytes)
            for ran in iterations:
                (hit,) = np.flatnonzero(ran.positions == position)[:1].tolist() or [None]
                if hit is not None:
                    d.spend(float(ran.compute_s[hit]), int(ran.env_steps[hit]), round_index,
                            grad_steps=int(ran.grad_steps[hit]), num_params=num_params)  # fmt: skip
            d.transmit(num_bytes)
            expected.append((d.take_emulated(), d.speed_at(round_index)))
        assert emulated.tolist() == [e for e, _ in expected]
        assert speeds.tolist() == [s for _, s in expected]
        assert len(set(emulated.tolist())) > 150


def test_column_wise_emulation_needs_the_virtual_clock() -> None:
    with pytest.raises(ValueError, match="virtual clock"):
        DeviceColumns([DeviceModel(virtual_clock=False)])
