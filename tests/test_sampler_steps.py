"""The torch sampler's time loop as fixed-shape steps: what one step costs in aten calls and
host synchronisations, counted at torch's dispatch, against the plain eager reference of
``make bench-device`` (benchmarks/device_reference.py) on the same agents × copies.

A step of the torch families steps every copy (an ended one masked out) and never waits for
the device: the sampler asks whether any copy still runs once every few steps (its end
checks), so between two checks there is no synchronisation at all, and no op whose output's
shape depends on the data (a GPU could run, or capture, a step without the host)."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from benchmarks.device_reference import Reference
from benchmarks.scale_device import balancing_theta
from fedhpg.common.heterogeneity.variants import variants_of
from fedhpg.common.learning.engine import copies as copies_module
from fedhpg.common.learning.engine import sampling
from fedhpg.common.learning.engine.engine import Engine
from fedhpg.common.learning.engine.sampling import END_CHECK
from fedhpg.common.learning.worker import initial_theta
from fedhpg.common.runtime.cli import compose

AGENTS, COPIES = 4, 16
HORIZON = 64
STEP = "STEP"
"""The marker a step of the copies leaves in the log."""

SYNCING = {
    "_local_scalar_dense", "item", "is_nonzero", "equal", "allclose", "nonzero", "argwhere",
    "masked_select", "unique", "_unique", "_unique2", "unique_dim", "unique_consecutive",
    "unique_dim_consecutive", "repeat_interleave", "masked_scatter",
}  # fmt: skip
"""aten ops that read a value back to the host, or whose output's shape depends on the data
(the host must wait for the device to size it)."""


class _Log(TorchDispatchMode):
    """Every aten call's name, in order; an indexing by a boolean mask is logged as
    ``masked index`` (its shape is the mask's count)."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[str] = []

    def __torch_dispatch__(
        self,
        func: Any,
        types: Any,
        args: tuple[Any, ...] = (),
        kwargs: dict[str, Any] | None = None,
    ) -> Any:
        name = func.overloadpacket.__name__
        if name in {"index", "index_put", "index_put_", "_index_put_impl_"}:
            indices = args[1] if len(args) > 1 else ()
            if any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices):
                name = "masked index"
        self.events.append(name)
        return func(*args, **(kwargs or {}))


def _syncs(events: list[str]) -> list[int]:
    return [i for i, name in enumerate(events) if name in SYNCING or name == "masked index"]


def _sampled(monkeypatch: pytest.MonkeyPatch, theta_of: Callable[[Any], torch.Tensor]) -> _Log:
    """One batch of CartPole's torch copies (AGENTS × COPIES, HORIZON steps) under the log,
    each step of the copies marked."""
    run = compose([
        "env=cartpole", "policy.hidden=[16,16]", f"agents.num_agents={AGENTS}",
        f"agents.budget.batch_size=[{COPIES}]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
        "algo.engine=torch", "algo.device=cpu",
    ])  # fmt: skip
    agents = list(range(AGENTS))
    engine = Engine(run, variants_of(run, agents))
    rows = engine.begin(1, theta_of(run), agents)
    log = _Log()
    step = copies_module.DeviceBlocks.step

    def marked(self: Any, *args: Any, **kwargs: Any) -> Any:
        log.events.append(STEP)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(copies_module.DeviceBlocks, "step", marked)
    counts = torch.full((AGENTS,), COPIES)
    horizons = torch.full((AGENTS,), HORIZON)
    with log:
        rows.sample(rows.theta, counts, iteration=0, horizons=horizons)
    return log


def _between_checks(events: list[str]) -> list[tuple[int, int]]:
    """(steps, aten calls) of the stretches of the time loop between two synchronisations."""
    marks = [i for i, name in enumerate(events) if name == STEP]
    inside = [i for i in _syncs(events) if marks[0] < i < marks[-1]]
    stretches = []
    for start, end in itertools.pairwise(inside):
        between = events[start + 1 : end]
        stretches.append((between.count(STEP), len(between) - between.count(STEP)))
    return stretches


def _reference_calls_per_step() -> float:
    """The reference's aten calls per step of its time loop, on the same AGENTS × COPIES on
    the CPU: the difference of two rollouts' counts over their difference in steps."""
    torch.manual_seed(0)
    reference = Reference(AGENTS, COPIES, torch.device("cpu"))
    counted = []
    for steps in (HORIZON // 2, HORIZON):
        with _Log() as log:
            reference.rollout(steps)
        counted.append(len(log.events))
    return (counted[1] - counted[0]) / (HORIZON - HORIZON // 2)


def test_a_step_waits_for_nothing_and_costs_what_the_reference_costs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Every pole balanced to the horizon: a stretch between two end checks is many steps
    with no synchronisation in any, and each step (the decision draws of a chunk included)
    makes at most 1.5 × the aten calls of the reference's step."""
    events = _sampled(monkeypatch, balancing_theta).events
    assert events.count(STEP) == HORIZON
    stretches = _between_checks(events)
    assert len(stretches) >= 2, stretches
    assert all(steps >= 8 for steps, _ in stretches), (
        f"a synchronisation inside a step: steps between two waits {stretches}"
    )
    ours = max(calls / steps for steps, calls in stretches)
    reference = _reference_calls_per_step()
    print(f"aten calls per step: ours {ours:.1f}, reference {reference:.1f}")
    assert ours <= 1.5 * reference, (ours, reference)


def _initial_batch(
    monkeypatch: pytest.MonkeyPatch, *, narrow_at: float | None = None
) -> tuple[Any, list[int]]:
    """Six CartPole agents' 16 copies each at θ̃₀, and the number of copies each step of the
    copies stepped (``narrow_at``: the sampler's :data:`NARROW_AT` instead of its own)."""
    widths: list[int] = []
    step = copies_module.DeviceBlocks.step

    def spy(self: Any, actions: torch.Tensor, *args: Any, **kwargs: Any) -> Any:
        widths.append(len(actions))
        return step(self, actions, *args, **kwargs)

    monkeypatch.setattr(copies_module.DeviceBlocks, "step", spy)
    if narrow_at is not None:
        monkeypatch.setattr(sampling, "NARROW_AT", narrow_at)
    run = compose([
        "env=cartpole", "algo.engine=torch", "policy.hidden=[8]", "agents.num_agents=6",
        "agents.budget.batch_size=[16]", "agents.speeds=[1]", "agents.step_delays_s=[0]",
    ])  # fmt: skip
    agents = list(range(6))
    engine = Engine(run, variants_of(run, agents))
    rows = engine.begin(1, initial_theta(variants_of(run, [0])[0], run), agents)
    return rows.sample(rows.theta, torch.full((6,), 16), iteration=0), widths


def test_tiles_whose_copies_all_ended_are_dropped_at_the_checks_and_the_batch_cut_at_its_longest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """At θ̃₀ episodes end at very different steps. Between two end checks every copy of the
    batch's current width is stepped (no synchronisation inside a step); at a check the batch
    keeps exactly the tiles (here an agent's 16 copies each) that hold a running copy, once
    they are at most NARROW_AT of those stepped; the loop stops at the first check with none
    running, and the batch is as long as its longest episode."""
    batch, widths = _initial_batch(monkeypatch)
    lengths = batch.alive.sum(0)
    longest = int(lengths.max())
    assert int(lengths.min()) < longest // 2  # episodes of very different lengths
    assert batch.alive.shape[0] == longest
    assert len(widths) == -(-longest // END_CHECK) * END_CHECK, "up to the next end check"
    assert torch.equal(batch.rewards != 0, batch.alive), "rewards where a copy ran, only"
    agent_longest = lengths.view(6, 16).max(1).values
    width = 96
    for t, stepped in enumerate(widths):
        if t % END_CHECK == 0 and t:
            running = 16 * int((agent_longest > t).sum())
            if running <= sampling.NARROW_AT * width:
                width = running
        assert stepped == width, (t, stepped, width)
    assert widths[-1] < widths[0], "the batch narrowed"


def test_a_narrowed_batch_is_the_batch_every_copy_stepped_to_the_end(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Dropping the tiles whose copies have all ended changes no trajectory: the same
    observations, actions, rewards, lengths and successes as a sampler that never narrows."""
    narrowed, widths = _initial_batch(monkeypatch)
    assert min(widths) < max(widths), "the batch narrowed"
    whole, widths = _initial_batch(monkeypatch, narrow_at=0.0)
    assert set(widths) == {96}, "never narrowed"
    alive = whole.alive
    assert torch.equal(narrowed.alive, alive)
    assert torch.equal(narrowed.lengths(), whole.lengths())
    assert torch.equal(narrowed.success, whole.success)
    assert torch.equal(narrowed.rewards, whole.rewards)
    assert torch.equal(narrowed.obs[alive], whole.obs[alive])
    assert torch.equal(narrowed.actions[alive], whole.actions[alive])
