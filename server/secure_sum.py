"""What a secure round's sum must satisfy before θ̃ takes it.

The server never sees one agent's contribution, only their sum, whose public parts it checks
(:mod:`fedhpg.common.privacy.contribution` builds each agent's row):

- The weight column, Σ w_u over the n inputs. An honest agent's w is 1 (``strategy=mean``) or
  its trajectories / ``WEIGHT_UNIT`` (``weighted``: at least one trajectory's worth, and at
  most the fixed-point range, to which the encoding clips every coordinate). A sum outside
  n·[w_min, w_max], give or take the fixed point's rounding, holds an input no honest agent
  sends (or an unmasking gone wrong): it would set the average's divisor.
- ``server.max_update_norm``, which cannot judge an update the server never sees, bounds the
  round's average step: an average of steps each within the bound is within it too (a
  weighted average of vectors is never longer than the longest), so a longer one holds at
  least one update beyond it, which one the server cannot tell. Under DP the step carries the
  round's noise.

A sum that fails is not adopted: the round is skipped and recorded (server/coordinator.py).
"""

from __future__ import annotations

import math

import numpy as np

from fedhpg.common.configuration.config import RunConfig
from fedhpg.common.privacy import fixedpoint
from fedhpg.common.privacy.contribution import WEIGHT_UNIT
from fedhpg.server.pools import SecureSum


def weight_range(run: RunConfig, weighted: bool) -> tuple[float, float]:
    """(lowest, highest) weight one honest agent's contribution carries."""
    if not weighted:
        return 1.0, 1.0
    return 1.0 / WEIGHT_UNIT, max(run.privacy.secagg.range, 1.0)


def sum_problem(
    run: RunConfig, secure: SecureSum, step: np.ndarray, *, weighted: bool
) -> str | None:
    """Why the round's sum (and the average ``step`` made of it) cannot be adopted; None if
    it can."""
    inputs = secure.inputs
    weights = float(secure.total[-2])
    lowest, highest = weight_range(run, weighted)
    # each input's weight was rounded to the fixed point: half a unit each
    slack = inputs / fixedpoint.scale_for(
        max(secure.participants, 1), max(run.privacy.secagg.range, 1.0)
    )
    if not (
        math.isfinite(weights) and inputs * lowest - slack <= weights <= inputs * highest + slack
    ):
        return (
            f"the sum's weights add up to {weights:.6g}, which {inputs} honest inputs cannot "
            f"(each weighs {lowest:g}"
            + ("" if lowest == highest else f" to {highest:g}")
            + "): θ̃ is not adopted"
        )
    bound = run.server.max_update_norm
    if bound is not None:
        norm = float(np.linalg.norm(step))
        if not norm <= bound:
            return (
                f"the round's average update moves θ by {norm:.4g} > "
                f"server.max_update_norm={bound:g} (some input is beyond it): θ̃ is not adopted"
            )
    return None
