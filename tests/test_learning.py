"""End to end: the demo federation learns a policy that solves every agent's GridWorld."""

from __future__ import annotations

import pytest

from fedhpg.common.runtime.cli import compose
from fedhpg.server.assembly import run_in_process
from fedhpg.server.coordinator import RoundRecord

THRESHOLD = 0.9


@pytest.mark.parametrize("algo", ["fedhpg", "fedhpgvr"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_demo_federation_solves_every_environment(algo: str, seed: int) -> None:
    run = compose([f"algo.name={algo}", f"seed={seed}", "rounds=100", "eval.every=5"])
    reached: list[int] = []

    def watch(record: RoundRecord, _: object) -> None:
        if record.eval and min(e.success_rate for e in record.eval.values()) >= THRESHOLD:
            reached.append(record.round)

    run_in_process(run, on_round=[watch])
    assert reached, f"{algo} seed {seed} never reached success ≥ {THRESHOLD} in every environment"
    assert reached[-1] == 100, "and it still solves them at the end"
