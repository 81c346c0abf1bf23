"""Policy-gradient estimators: REINFORCE (paper eq. 5) and GPOMDP (eq. 6), as pure functions.

Both estimators are linear in the per-step scores ∇ log π(a_t|s_t), so each reduces to one
coefficient per (step, trajectory):

    g(τ_b | θ) = Σ_t coef[t, b] · ∇ log π_θ(a_t | s_t)

The coefficient functions below are the maths; :func:`estimate_gradient` turns coefficients
into the batch gradient (1/B) Σ_b g(τ_b) with one autograd pass over the whole batch, and
:func:`per_trajectory_gradients` gives every g(τ_b) (for tests and variance statistics).

Baselines. ``"mean"`` uses, for trajectory b, the mean over the *other* trajectories of the
batch (leave-one-out): a baseline built from the same batch including τ_b itself would bias the
estimate by a factor (B−1)/B; leaving τ_b out keeps it unbiased. With B = 1 it is 0.

Importance weights (FedHPGVR). REINFORCE takes one weight per trajectory [B]; GPOMDP takes the
per-decision cumulative weights w_{0:h} [T, B] and weighs the reward at step h with w_{0:h}.

Options used in practice (``algo.reward_to_go``, ``algo.normalize``), **departures from eq. 5/6
and biased for ∇J** (README, Estimator options, gives their measured bias): GPOMDP's reward-to-go
discounted from the scored step, Σ_{h≥t} γ^{h−t} r_h instead of Σ_{h≥t} γ^h r_h (it drops the
γ^t that makes late steps count less in the discounted objective), and standardising the
coefficients within the batch or within each episode (the mean and spread come from the very
samples they rescale). The defaults, ``from_start`` and ``none``, are eq. 5/6 exactly.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch.func import functional_call, grad, vmap

from fedhpg.common.configuration.vocabularies import BASELINES, ESTIMATORS
from fedhpg.common.learning.policies import Policy, flat_grad
from fedhpg.common.learning.staircase import Staircase, ordered_sums

EstimatorName = str
"""A name in :data:`~fedhpg.common.configuration.vocabularies.ESTIMATORS` (an open vocabulary)."""
BaselineName = str
"""A name in :data:`~fedhpg.common.configuration.vocabularies.BASELINES`."""
RewardToGoName = Literal["from_start", "from_step"]
NormalizeName = Literal["none", "batch", "episode"]

# Added to a standard deviation before dividing by it: a batch or episode whose coefficients
# are all equal (e.g. every CartPole step of a batch alive with the mean baseline) gives 0, not NaN.
NORMALIZE_EPS = 1e-8


Gamma = float | torch.Tensor
"""A discount: one for every trajectory, or one per trajectory (column) [B]."""


def _leave_one_out_mean(values: torch.Tensor, groups: torch.Tensor | None) -> torch.Tensor:
    """For each entry of [N], the mean of the other entries of its group (0 where the group
    has one entry). ``groups`` [N]: each entry's group (one agent's batch); None: one group."""
    if groups is None:
        count = values.shape[-1]
        if count == 1:
            return torch.zeros_like(values)
        return (values.sum(dim=-1, keepdim=True) - values) / (count - 1)
    size = int(groups.max()) + 1 if groups.numel() else 0
    totals = ordered_sums(groups, values, size)
    counts = torch.bincount(groups, minlength=size).to(values.dtype)
    loo = (totals[groups] - values) / (counts - 1).clamp_min(1.0)[groups]
    return torch.where(counts[groups] > 1, loo, torch.zeros_like(loo))


def _less_step_baseline(
    layout: Staircase, values: torch.Tensor, groups: torch.Tensor
) -> torch.Tensor:
    """x = values − C per cell [S], ready for :meth:`Staircase.tail_sums`, with C[t, n] the
    mean of ``values`` at step t over the other columns of n's group, every column of the
    group counted (a column past its end holds 0): x = v − (S_t − v)/o = v (1 + 1/o) − S_t/o,
    S_t the group's sum at step t, o its other columns (a group of one column keeps v
    exactly: 2v − v). Every column must reach its group's longest (past its end x = −S_t/o,
    which its tail sum needs)."""
    if not (layout.grouped or layout.dense):
        raise ValueError(
            "a per-step baseline needs every column to its group's longest "
            "(Staircase.of_groups or a padded layout)"
        )
    size = int(groups.max()) + 1
    others = (torch.bincount(groups, minlength=size) - 1).clamp_min(1).to(values.dtype)
    extents = layout.extents
    longest = extents.new_zeros(size).scatter_reduce(0, groups, extents, "amax")
    table = Staircase(longest)  # (t, g) for each group's steps
    shares = layout.step_group_sums(values, groups, table) / table.per_cell(others)
    out = values * layout.per_cell((1.0 + 1.0 / others).index_select(0, groups))
    out.sub_(layout.per_step_group(shares, groups, table))
    return out


def _discounts(gamma: Gamma, layout: Staircase, like: torch.Tensor) -> torch.Tensor:
    """γ^t of every cell, [S] (each column's own γ where ``gamma`` is [N])."""
    if not isinstance(gamma, torch.Tensor):
        gamma = torch.full((layout.columns,), gamma, dtype=like.dtype, device=like.device)
    return layout.step_powers(gamma.to(like.dtype))


def _cell_weights(layout: Staircase, weights: torch.Tensor) -> torch.Tensor:
    """Importance weights per cell: [N] (one per trajectory) spread over its cells, or [S]."""
    return layout.per_cell(weights) if weights.shape[0] == layout.columns else weights


def coefficients(
    estimator: EstimatorName,
    layout: Staircase,
    rewards: torch.Tensor,
    alive: torch.Tensor | None,
    *,
    gamma: Gamma,
    baseline: BaselineName = "mean",
    weights: torch.Tensor | None = None,
    reward_to_go: RewardToGoName = "from_start",
    normalize: NormalizeName = "none",
    groups: torch.Tensor | None = None,
) -> torch.Tensor:
    """coef[t, n] of every cell of ``layout`` (``rewards``, ``alive``: [S], ``alive`` None
    where every cell is a step that happened; ``gamma``: one or per column [N]; ``groups``
    [N]: each column's agent, whose other trajectories make its baselines; ``weights``:
    importance weights, [N] per trajectory or [S] per cell).

    ``layout`` extends each column to its group's longest (:meth:`Staircase.of_groups`):
    GPOMDP's per-step baseline reaches every such cell (ValueError otherwise).

    REINFORCE, eq. (5): coef[t, n] = w_n · (Σ_h γ^h r_{h,n} − C_n) on alive steps, C_n the
    mean return of the other trajectories of n's agent.

    GPOMDP, eq. (6): coef[t, n] = Σ_{h ≥ t} w_{0:h,n} · (γ^h r_{h,n} − C_{h,n}) on alive
    steps. The per-step baseline C_h is applied at every step h < T, dead steps included:
    masking it by "still alive at h" would correlate it with the earlier actions and bias
    the estimate. ``reward_to_go="from_step"`` (a departure, biased): Σ_{h ≥ t} w_{0:h,n} ·
    γ^{h−t} (r_{h,n} − C_{h,n}), eq. (6)'s coefficient divided by γ^t.

    Then ``normalize`` (a departure, biased): the coefficients standardised over the alive
    cells of each agent's batch (``"batch"``) or of each trajectory (``"episode"``).
    """
    per_step = ESTIMATORS.get(estimator).per_step  # a ConfigError (a ValueError) if unknown
    subtracts_mean = BASELINES.get(baseline).subtracts_mean
    group = (
        groups
        if groups is not None
        else torch.zeros(layout.columns, dtype=torch.int64, device=rewards.device)
    )
    mask = None if alive is None else alive.to(rewards.dtype)
    if not per_step:
        if reward_to_go != "from_start":
            raise ValueError("reward_to_go='from_step' needs estimator 'gpomdp'")
        totals = layout.column_totals(_discounts(gamma, layout, rewards).mul_(rewards))
        centred = totals - _leave_one_out_mean(totals, group) if subtracts_mean else totals
        if weights is not None:
            if weights.shape[0] != layout.columns:
                raise ValueError("REINFORCE takes one importance weight per trajectory")
            centred = centred * weights
        coef = layout.per_cell(centred)
        if mask is not None:
            coef = mask * coef
    else:
        discounted = reward_to_go == "from_start"
        values = _discounts(gamma, layout, rewards).mul_(rewards) if discounted else rewards
        factors = None
        if not discounted:
            factors = (
                gamma.to(rewards.dtype)
                if isinstance(gamma, torch.Tensor)
                else torch.full(
                    (layout.columns,), gamma, dtype=rewards.dtype, device=rewards.device
                )
            )
        if subtracts_mean:
            values = _less_step_baseline(layout, values, group)
        if weights is not None:
            values = values * _cell_weights(layout, weights)
        coef = layout.tail_sums(values, factors)
        if mask is not None:
            coef.mul_(mask)
    return _normalized(layout, coef, mask, normalize, group)


def _normalized(
    layout: Staircase,
    coef: torch.Tensor,
    mask: torch.Tensor | None,
    mode: NormalizeName,
    groups: torch.Tensor,
) -> torch.Tensor:
    """(c − mean) / (std + ε) over the alive cells of each group or each column, 0 on dead
    cells (a departure from eq. 5/6, biased: the mean and std come from the samples they
    rescale, so E[g] is neither ∇J nor a fixed multiple of it; README, Estimator options)."""
    if mode == "none":
        return coef
    if mask is None:
        mask = torch.ones_like(coef)
    key = layout.column if mode == "episode" else layout.per_cell(groups)
    size = layout.columns if mode == "episode" else int(groups.max()) + 1

    def sums(values: torch.Tensor) -> torch.Tensor:
        return ordered_sums(key, values, size)

    count = sums(mask).clamp_min(1.0)
    centred = coef - (sums(coef * mask) / count).index_select(0, key)
    spread = sums(centred**2 * mask) / count
    return mask * centred / (spread.sqrt().index_select(0, key) + NORMALIZE_EPS)


def estimator_coefficients(
    estimator: EstimatorName,
    rewards: torch.Tensor,
    alive: torch.Tensor,
    *,
    gamma: Gamma,
    baseline: BaselineName = "mean",
    weights: torch.Tensor | None = None,
    reward_to_go: RewardToGoName = "from_start",
    normalize: NormalizeName = "none",
    groups: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`coefficients` of a padded batch: ``rewards``, ``alive`` [T, B]; ``weights`` [B]
    or [T, B]; returns [T, B] (0 on dead steps)."""
    layout = Staircase.padded(rewards.shape[0], rewards.shape[1], rewards.device)
    cells = coefficients(
        estimator,
        layout,
        rewards.reshape(-1),
        alive.reshape(-1),
        gamma=gamma,
        baseline=baseline,
        weights=None if weights is None else weights.reshape(-1),
        reward_to_go=reward_to_go,
        normalize=normalize,
        groups=groups,
    )
    return layout.pad(cells)


def normalize_coefficients(
    coefficients: torch.Tensor,
    alive: torch.Tensor,
    mode: NormalizeName,
    groups: torch.Tensor | None = None,
) -> torch.Tensor:
    """The normalisation step of :func:`coefficients` alone, on padded [T, B] coefficients."""
    layout = Staircase.padded(coefficients.shape[0], coefficients.shape[1], alive.device)
    group = (
        groups
        if groups is not None
        else torch.zeros(layout.columns, dtype=torch.int64, device=alive.device)
    )
    mask = alive.reshape(-1).to(coefficients.dtype)
    return layout.pad(_normalized(layout, coefficients.reshape(-1), mask, mode, group))


def estimate_gradient(
    policy: Policy, obs: torch.Tensor, actions: torch.Tensor, coefficients: torch.Tensor
) -> torch.Tensor:
    """(1/B) Σ_b Σ_t coef[t, b] ∇ log π_θ(a_t|s_t) as one flat vector (one autograd pass)."""
    log_probs = policy.log_prob(obs, actions)  # [T, B]
    surrogate = (coefficients.detach().to(log_probs.dtype) * log_probs).sum() / log_probs.shape[1]
    return flat_grad(surrogate, policy)


def per_trajectory_gradients(
    policy: Policy, obs: torch.Tensor, actions: torch.Tensor, coefficients: torch.Tensor
) -> torch.Tensor:
    """Every g(τ_b) as rows of a [B, d] matrix (per-trajectory gradients via ``vmap``; for
    tests and diagnostics)."""
    params = {name: p.detach() for name, p in policy.named_parameters()}

    def surrogate(
        p: dict[str, torch.Tensor], obs_b: torch.Tensor, act_b: torch.Tensor, coef_b: torch.Tensor
    ) -> torch.Tensor:
        log_probs = functional_call(policy, p, (obs_b, act_b))  # [T]
        return (coef_b.to(log_probs.dtype) * log_probs).sum()

    grads = vmap(grad(surrogate), in_dims=(None, 1, 1, 1))(
        params, obs, actions, coefficients.detach()
    )
    return torch.cat([grads[name].reshape(coefficients.shape[1], -1) for name in params], dim=1)


def clip_rows(
    gradient: torch.Tensor, max_norm: float | None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Scale each row of [A, d] down to norm ``max_norm`` (Assumption 3); returns the rows and
    which were clipped [A] (None without a ``max_norm``: none)."""
    if max_norm is None:
        return gradient, None
    norms = gradient.double().norm(dim=1)
    clipped = norms > max_norm
    scale = torch.where(clipped, max_norm / norms.clamp_min(1e-300), torch.ones_like(norms))
    return gradient * scale.to(gradient.dtype).unsqueeze(1), clipped


def clip_by_norm(gradient: torch.Tensor, max_norm: float | None) -> tuple[torch.Tensor, bool]:
    """Scale ``gradient`` down to norm ``max_norm`` (Assumption 3); returns (g, was_clipped)."""
    rows, clipped = clip_rows(gradient.unsqueeze(0), max_norm)
    return (rows[0], True) if clipped is not None and bool(clipped[0]) else (gradient, False)
