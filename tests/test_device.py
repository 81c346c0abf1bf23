"""The emulated device: speed factor, env-step throttle, latency, time-varying schedules."""

from __future__ import annotations

import math
import time

import pytest
import torch

from fedhpg.common.heterogeneity.device import DeviceModel
from fedhpg.common.learning.estimators import clip_by_norm


def test_virtual_clock_accounts_without_sleeping() -> None:
    device = DeviceModel(speed=0.25, step_delay_s=0.001, virtual_clock=True)
    started = time.perf_counter()
    emulated = device.spend(real_s=0.5, env_steps=100, round_index=1)
    assert time.perf_counter() - started < 0.1
    assert emulated == pytest.approx(0.5 / 0.25 + 100 * 0.001)
    assert device.take_emulated() == pytest.approx(2.1)
    assert device.take_emulated() == 0.0


def test_real_clock_sleeps_the_difference_once_when_the_round_settles() -> None:
    slept: list[float] = []
    device = DeviceModel(speed=0.5, latency_s=0.02, sleep=slept.append)
    device.transmit()  # owes 0.02
    device.spend(real_s=0.05, env_steps=0, round_index=1)  # owes 0.1 - 0.05
    device.spend(real_s=0.05, env_steps=0, round_index=1)
    assert slept == [], "no sleep between iterations: it would disturb the compute measured"
    device.settle()
    assert slept == [pytest.approx(0.02 + 0.05 + 0.05)]
    device.settle()
    assert len(slept) == 1, "paid once"
    assert device.take_emulated() == pytest.approx(0.02 + 0.1 + 0.1)


def test_real_clock_really_sleeps() -> None:
    device = DeviceModel(speed=0.5, latency_s=0.02)
    started = time.perf_counter()
    device.spend(real_s=0.05, env_steps=0, round_index=1)
    device.transmit()
    device.settle()
    assert time.perf_counter() - started >= 0.07


def test_a_cancelled_rounds_sleep_is_forgiven() -> None:
    slept: list[float] = []
    device = DeviceModel(speed=0.25, sleep=slept.append)
    device.spend(real_s=0.1, env_steps=0, round_index=1)  # the round is cancelled here
    device.take_emulated()  # the next round starts
    device.spend(real_s=0.1, env_steps=0, round_index=2)
    device.settle()
    assert slept == [pytest.approx(0.3)]


def test_the_virtual_clock_owes_nothing() -> None:
    slept: list[float] = []
    device = DeviceModel(speed=0.25, latency_s=0.5, virtual_clock=True, sleep=slept.append)
    device.spend(real_s=0.1, env_steps=0, round_index=1)
    device.transmit()
    device.settle()
    assert slept == [] and device.take_emulated() == pytest.approx(0.9)


def test_periodic_schedule() -> None:
    device = DeviceModel(speed=1.0, schedule="periodic", period_rounds=4, amplitude=0.5)
    speeds = [device.speed_at(r) for r in range(1, 6)]
    assert speeds == pytest.approx([1.0, 1.5, 1.0, 0.5, 1.0])


def test_random_walk_is_bounded_and_reproducible() -> None:
    def walk(seed: int) -> list[float]:
        device = DeviceModel(speed=0.5, schedule="random_walk", amplitude=0.4, seed=seed)
        return [device.speed_at(r) for r in range(1, 60)]

    first = walk(3)
    assert first == walk(3)
    assert first != walk(4)
    assert all(0.5 * 0.6 - 1e-12 <= s <= 0.5 * 1.4 + 1e-12 for s in first)
    assert len({round(s, 6) for s in first}) > 10, "the speed really varies"
    device = DeviceModel(speed=0.5, schedule="random_walk", amplitude=0.4, seed=3)
    assert device.speed_at(30) == first[29] and device.speed_at(2) == first[1], "random access"


def test_gradient_clipping() -> None:
    gradient = torch.tensor([3.0, 4.0])
    clipped, was = clip_by_norm(gradient, 1.0)
    assert was and math.isclose(float(clipped.norm()), 1.0, rel_tol=1e-6)
    same, was = clip_by_norm(gradient, 10.0)
    assert not was and torch.equal(same, gradient)
    assert clip_by_norm(gradient, None) == (gradient, False)
