"""The reference ``make bench-device`` measures the engine against: K agents' CartPole on one
device in plain eager PyTorch, written apart from the engine (none of its code).

K agents × C copies of CartPole-v1 with gymnasium's constants, stepped with its Euler
equations for T steps, each copy reset (uniform in ±0.05) as soon as its episode ends;
every agent's own 16-16 tanh MLP evaluated as a batched matrix product over agents, one
categorical draw per copy and step. With the gradient: the stored T-step trajectory's
REINFORCE loss (each step's log-probability times its discounted reward-to-go within its
episode), one autograd backward pass and a plain gradient step of every agent's MLP. No CUDA
graphs, no compilation. Every copy is alive at every step, so its steps per second count
K·C·T steps per iteration.

    python -m benchmarks.device_reference --device cuda --agents 65536
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import torch

GRAVITY, MASSCART, MASSPOLE, LENGTH, FORCE, TAU = 9.8, 1.0, 0.1, 0.5, 10.0, 0.02
TOTAL_MASS = MASSCART + MASSPOLE
POLEMASS_LENGTH = MASSPOLE * LENGTH
THETA_LIMIT, X_LIMIT = 12 * 2 * math.pi / 360, 2.4
GAMMA = 0.99
STEP_SIZE = 1e-3


@dataclass(frozen=True)
class Measured:
    steps_per_s: float
    """Env steps per second (K·C·T per iteration)."""
    seconds: float
    """One iteration (the median of the repeats)."""
    peak_bytes: int | None
    """The device's peak allocation (CUDA), None on the CPU."""


class Reference:
    """K agents' MLPs and their C copies' states on one device."""

    def __init__(self, agents: int, copies: int, device: torch.device, hidden: int = 16) -> None:
        self.agents, self.copies, self.device = agents, copies, device
        generator = torch.Generator(device=device).manual_seed(0)

        def layer(fan_in: int, fan_out: int) -> list[torch.Tensor]:
            bound = 1 / math.sqrt(fan_in)
            shape = (agents, fan_in, fan_out)
            weight = (torch.rand(shape, generator=generator, device=device) * 2 - 1) * bound
            bias = torch.zeros(agents, 1, fan_out, device=device)
            return [weight.requires_grad_(), bias.requires_grad_()]

        self.params = [*layer(4, hidden), *layer(hidden, hidden), *layer(hidden, 2)]
        self.generator = generator
        self.state = self._starts(agents * copies)

    def _starts(self, count: int) -> torch.Tensor:
        return torch.rand(count, 4, generator=self.generator, device=self.device) * 0.1 - 0.05

    def logits(self, obs: torch.Tensor) -> torch.Tensor:
        """obs [K, R, 4] -> logits [K, R, 2], each agent's own MLP."""
        w1, b1, w2, b2, w3, b3 = self.params
        hidden = torch.tanh(torch.baddbmm(b1, obs, w1))
        hidden = torch.tanh(torch.baddbmm(b2, hidden, w2))
        return torch.baddbmm(b3, hidden, w3)

    def physics(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x, x_dot, theta, theta_dot = state.unbind(1)
        force = torch.where(action == 1, FORCE, -FORCE)
        cos, sin = torch.cos(theta), torch.sin(theta)
        temp = (force + POLEMASS_LENGTH * theta_dot * theta_dot * sin) / TOTAL_MASS
        theta_acc = (GRAVITY * sin - cos * temp) / (
            LENGTH * (4.0 / 3.0 - MASSPOLE * cos * cos / TOTAL_MASS)
        )
        x_acc = temp - POLEMASS_LENGTH * theta_acc * cos / TOTAL_MASS
        return torch.stack(
            (x + TAU * x_dot, x_dot + TAU * x_acc, theta + TAU * theta_dot,
             theta_dot + TAU * theta_acc), dim=1,
        )  # fmt: skip

    @torch.no_grad()
    def rollout(self, steps: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """T steps of every copy: observations [T, N, 4], actions, rewards and ends [T, N]."""
        n = self.agents * self.copies
        observations = torch.empty(steps, n, 4, device=self.device)
        actions = torch.empty(steps, n, dtype=torch.int64, device=self.device)
        ended = torch.empty(steps, n, dtype=torch.bool, device=self.device)
        state = self.state
        for t in range(steps):
            observations[t] = state
            logits = self.logits(state.view(self.agents, self.copies, 4)).view(n, 2)
            right = torch.sigmoid(logits[:, 1] - logits[:, 0])
            u = torch.rand(n, generator=self.generator, device=self.device)
            action = (u < right).long()
            state = self.physics(state, action)
            done = (state[:, 0].abs() > X_LIMIT) | (state[:, 2].abs() > THETA_LIMIT)
            state = torch.where(done.unsqueeze(1), self._starts(n), state)
            actions[t], ended[t] = action, done
        self.state = state
        rewards = torch.ones(steps, n, device=self.device)
        return observations, actions, rewards, ended

    def update(self, observations: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor,
               ended: torch.Tensor) -> None:  # fmt: skip
        """One REINFORCE gradient over the stored trajectory and a plain step."""
        steps, n = actions.shape
        to_go = torch.zeros(n, device=self.device)
        returns = torch.empty_like(rewards)
        for t in range(steps - 1, -1, -1):  # reward-to-go, restarted at each episode's end
            to_go = rewards[t] + GAMMA * to_go * (~ended[t])
            returns[t] = to_go
        obs = observations.view(steps, self.agents, self.copies, 4).transpose(0, 1)
        logits = self.logits(obs.reshape(self.agents, steps * self.copies, 4))
        log_pi = torch.log_softmax(logits, dim=-1)
        chosen = actions.view(steps, self.agents, self.copies).transpose(0, 1)
        taken = log_pi.gather(-1, chosen.reshape(self.agents, -1, 1)).squeeze(-1)
        weights = returns.view(steps, self.agents, self.copies).transpose(0, 1)
        loss = -(taken * weights.reshape(self.agents, -1)).sum() / self.copies
        gradients = torch.autograd.grad(loss, self.params)
        with torch.no_grad():
            for param, gradient in zip(self.params, gradients, strict=True):
                param -= STEP_SIZE * gradient


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(
    agents: int,
    copies: int,
    device: torch.device,
    *,
    steps: int = 64,
    gradient: bool,
    repeats: int = 3,
) -> Measured:
    """Steps per second of ``repeats`` iterations after one unmeasured (the sampling alone, or
    with the gradient and the step)."""
    reference = Reference(agents, copies, device)
    cuda = device.type == "cuda"
    times = []
    for repeat in range(repeats + 1):
        if cuda and repeat == 1:
            torch.cuda.reset_peak_memory_stats(device)
        _sync(device)
        started = time.perf_counter()
        batch = reference.rollout(steps)
        if gradient:
            reference.update(*batch)
        _sync(device)
        if repeat:
            times.append(time.perf_counter() - started)
        del batch
    seconds = sorted(times)[len(times) // 2]
    return Measured(
        steps_per_s=agents * copies * steps / seconds,
        seconds=seconds,
        peak_bytes=torch.cuda.max_memory_allocated(device) if cuda else None,
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--copies", type=int, default=16)
    parser.add_argument("--steps", type=int, default=64)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    device = torch.device(args.device)
    for gradient in (False, True):
        got = measure(args.agents, args.copies, device, steps=args.steps, gradient=gradient)
        what = "sampling + gradient + step" if gradient else "sampling"
        print(f"{args.agents:,} × {args.copies}: {what}: {got.steps_per_s / 1e6:.3g} M steps/s")


if __name__ == "__main__":
    main()
