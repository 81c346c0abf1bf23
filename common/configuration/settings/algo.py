"""The ``algo`` section: the algorithm, its estimator options, optimiser, engine and device
(read by :mod:`fedhpg.common.learning.algorithms` and :mod:`fedhpg.common.learning.engine`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from fedhpg.common.configuration.settings.checks import check_choice, check_number, require
from fedhpg.common.configuration.vocabularies import BASELINES, ESTIMATORS

REWARD_TO_GO: tuple[str, ...] = ("from_start", "from_step")
NORMALIZE: tuple[str, ...] = ("none", "batch", "episode")
OPTIMIZERS = ("sgd", "adam")
ENGINES = ("auto", "torch")
ENV_PATHS = ("auto", "gymnasium")
DEVICE_PATTERN = re.compile(r"cpu|cuda(:\d+)?")
"""``algo.device``: a torch device name the torch engine accepts."""


@dataclass(kw_only=True)
class AlgoConfig:
    """The federated algorithm (agent side) and the local policy-gradient settings it uses."""

    name: str = "fedhpg"
    """A registered algorithm: 'fedhpg' (Algorithm 1), 'fedhpgvr' (Algorithm 2), or a plugin's."""
    estimator: str = "gpomdp"
    """'reinforce' (eq. 5) or 'gpomdp' (eq. 6)."""
    baseline: str = "mean"
    """'none' or 'mean' (leave-one-out batch mean: C_b for REINFORCE, C_bh for GPOMDP)."""
    step_size: float = 1.0
    """Step size η of the local gradient ascent."""
    optimizer: str = "sgd"
    """'sgd' (plain ascent, as in the paper) or 'adam' (state reset every round)."""
    grad_clip: float | None = None
    """Clip each local gradient estimate to this norm; None = off (the default). Biased for
    ∇J: a clipped estimate's mean is not the gradient (about 6 % off with the clip at 2‖∇J‖,
    40 % at ‖∇J‖ on a small tabular MDP); Assumption 3 bounds the gradient, it does not ask
    for a clip (docs/configuration.md, Estimator options)."""
    params: dict[str, Any] = field(default_factory=dict)
    """The algorithm's own options (its ``Params`` dataclass), e.g. FedHPGVR's ``iw_mode``."""
    engine: str = "auto"
    """Which backend supplies the engine's primitives (``common/learning/engine``: every algorithm's
    one loop runs on either). 'torch': all of the process's agents sampled and differentiated
    together in torch on ``algo.device``, for every policy and family; 'auto': the same,
    except that honest agents with the MLP categorical policy on CartPole on the CPU are
    sampled and differentiated by the compiled numba backend (``common/learning/batched``, several
    times faster there). The two round floats differently, so the server dictates the
    choice; within either an agent's θ does not depend on where it runs or with whom."""
    device: str = "cpu"
    """The torch device of the engine: 'cpu', 'cuda' or 'cuda:N'."""
    envs: str = "auto"
    """Where the torch engine's environments step: 'auto' in torch on ``algo.device`` for the
    families with a torch implementation (cartpole, acrobot, pendulum, mountaincar,
    gridworld: ``envs/device/``), through gymnasium on the CPU for the others; 'gymnasium'
    through gymnasium for every family (the reference the torch families are checked
    against). Their floats differ (float32 against gymnasium's float64), so the server
    dictates it."""
    memory_gib: float | None = None
    """What one process's engine may hold at once on ``algo.device``, in GiB: a round of more
    agents than fit is trained in chunks of agents, one after another (θ does not depend on
    it). None: 80% of the free memory of a CUDA device, 2 GiB on the CPU
    (``common/learning/engine/memory.py``, docs/gpu.md)."""
    bound_estimates: bool = False
    """Estimate Theorem 1's constants every round (``common/learning/bounds.py``): each agent's σ̂²,
    M̂ and ‖∇J_k‖² at θ̃ from the per-trajectory gradients of its first local batch, written as
    ``bound_variance``, ``bound_second_moment`` and ``bound_grad_norm_sq`` in its ``algorithm``
    statistics, and with τ_k ≥ 2 ``bound_smoothness`` (L̂, the secant between its first two
    iterations' gradients). About two more gradients per round; θ̃ is the same either way.
    FedHPG only."""
    reward_to_go: str = "from_start"
    """GPOMDP's reward-to-go: 'from_start' (eq. 6, Σ_{h≥t} γ^h r_h; unbiased) or 'from_step'
    (Σ_{h≥t} γ^{h−t} r_h, common practice: a departure from eq. 6, biased for ∇J;
    docs/configuration.md, Estimator options). 'from_step' needs estimator 'gpomdp'; FedHPGVR
    takes 'from_start' only."""
    normalize: str = "none"
    """Standardise the estimator's coefficients, (c − mean)/std over alive steps: 'none' (eq.
    5/6; unbiased), 'batch' (over the whole batch) or 'episode' (within each trajectory; GPOMDP
    only). Both are departures from eq. 5/6, biased for ∇J (docs/configuration.md, Estimator
    options); FedHPGVR takes 'none' only."""


def validate_algo(algo: AlgoConfig) -> None:
    check_choice(algo.estimator, "algo.estimator", ESTIMATORS)
    check_choice(algo.baseline, "algo.baseline", BASELINES)
    check_choice(algo.reward_to_go, "algo.reward_to_go", REWARD_TO_GO)
    check_choice(algo.normalize, "algo.normalize", NORMALIZE)
    if not ESTIMATORS.get(algo.estimator).per_step:
        require(
            algo.reward_to_go == "from_start",
            "algo.reward_to_go",
            f"'from_step' needs algo.estimator=gpomdp (got {algo.estimator!r})",
        )
        require(
            algo.normalize != "episode",
            "algo.normalize",
            f"'episode' needs algo.estimator=gpomdp: {algo.estimator!r}'s coefficients are "
            "constant along a trajectory, so they would all become 0",
        )
    check_choice(algo.optimizer, "algo.optimizer", OPTIMIZERS)
    check_choice(algo.engine, "algo.engine", ENGINES)
    check_choice(algo.envs, "algo.envs", ENV_PATHS)
    if algo.memory_gib is not None:
        check_number(algo.memory_gib, "algo.memory_gib", low=0.0, low_open=True)
    require(
        isinstance(algo.device, str) and DEVICE_PATTERN.fullmatch(algo.device) is not None,
        "algo.device",
        f"got {algo.device!r}, allowed: cpu, cuda, cuda:N",
    )
    check_number(algo.step_size, "algo.step_size", low=0.0, low_open=True)
    if algo.grad_clip is not None:
        check_number(algo.grad_clip, "algo.grad_clip", low=0.0, low_open=True)
