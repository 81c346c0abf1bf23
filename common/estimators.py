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

from fedhpg.common.config import ESTIMATORS
from fedhpg.common.policies import Policy, flat_grad

EstimatorName = Literal["reinforce", "gpomdp"]
BaselineName = Literal["none", "mean"]
RewardToGoName = Literal["from_start", "from_step"]
NormalizeName = Literal["none", "batch", "episode"]

# Added to a standard deviation before dividing by it: a batch or episode whose coefficients
# are all equal (e.g. every CartPole step of a batch alive with the mean baseline) gives 0, not NaN.
NORMALIZE_EPS = 1e-8


Gamma = float | torch.Tensor
"""A discount: one for every trajectory, or one per trajectory (column) [B]."""


def _leave_one_out_mean(values: torch.Tensor, groups: torch.Tensor | None) -> torch.Tensor:
    """For each column b of [..., B], the mean of the other columns of its group (0 where
    the group has one column). ``groups`` [B]: each column's group (one agent's batch);
    None: every column in one group."""
    if groups is None:
        count = values.shape[-1]
        if count == 1:
            return torch.zeros_like(values)
        return (values.sum(dim=-1, keepdim=True) - values) / (count - 1)
    size = int(groups.max()) + 1 if groups.numel() else 0
    totals = values.new_zeros((*values.shape[:-1], size)).index_add_(-1, groups, values)
    counts = torch.bincount(groups, minlength=size).to(values.dtype)
    others = (counts - 1).clamp_min(1.0)[groups]
    loo = (totals.index_select(-1, groups) - values) / others
    return torch.where(counts[groups] > 1, loo, torch.zeros_like(loo))


def _discounts(gamma: Gamma, length: int, like: torch.Tensor) -> torch.Tensor:
    """γ^t for t < length: [T], or [T, B] for per-column discounts."""
    steps = torch.arange(length, dtype=like.dtype, device=like.device)
    if isinstance(gamma, torch.Tensor):
        return gamma.to(like.dtype).unsqueeze(0) ** steps.unsqueeze(1)
    return gamma**steps


def reinforce_coefficients(
    rewards: torch.Tensor,
    alive: torch.Tensor,
    *,
    gamma: Gamma,
    baseline: BaselineName = "mean",
    weights: torch.Tensor | None = None,
    groups: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eq. (5): coef[t, b] = w_b · (Σ_h γ^h r_{h,b} − C_b) on alive steps.

    rewards, alive: [T, B]; weights: optional [B] importance weights; ``groups``: each
    column's agent, for a batch of several agents' trajectories (the baseline C_b is the mean
    over the other trajectories of b's own agent).
    """
    discounts = _discounts(gamma, rewards.shape[0], rewards)
    returns = (discounts.reshape(rewards.shape[0], -1) * rewards).sum(dim=0)  # [B]
    centred = returns - _leave_one_out_mean(returns, groups) if baseline == "mean" else returns
    if weights is not None:
        centred = centred * weights
    return alive.to(rewards.dtype) * centred.unsqueeze(0)


def gpomdp_coefficients(
    rewards: torch.Tensor,
    alive: torch.Tensor,
    *,
    gamma: Gamma,
    baseline: BaselineName = "mean",
    weights: torch.Tensor | None = None,
    reward_to_go: RewardToGoName = "from_start",
    groups: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eq. (6): coef[t, b] = Σ_{h ≥ t} w_{0:h,b} · (γ^h r_{h,b} − C_{h,b}) on alive steps.

    The per-step baseline C_h is applied at every step h < T, dead steps included: masking it
    by "still alive at h" would correlate it with the earlier actions and bias the estimate.
    weights: optional [T, B] per-decision cumulative importance weights; ``groups`` as in
    :func:`reinforce_coefficients`.

    ``reward_to_go="from_step"`` (a departure, biased): Σ_{h ≥ t} w_{0:h,b} · γ^{h−t} (r_{h,b} −
    C_{h,b}), i.e. eq. (6)'s coefficient divided by γ^t; computed by the backward recursion
    R_t = x_t + γ R_{t+1}, so no γ^{−t} is ever formed (it would overflow on long horizons).
    """
    if reward_to_go == "from_step":
        step_values = (
            rewards - _leave_one_out_mean(rewards, groups) if baseline == "mean" else rewards
        )
        if weights is not None:
            step_values = step_values * weights
        return alive.to(rewards.dtype) * _discounted_tail_sums(step_values, gamma)
    discounts = _discounts(gamma, rewards.shape[0], rewards)
    step_rewards = discounts.reshape(rewards.shape[0], -1) * rewards  # [T, B]
    if baseline == "mean":
        step_rewards = step_rewards - _leave_one_out_mean(step_rewards, groups)
    if weights is not None:
        step_rewards = step_rewards * weights
    tail_sums = step_rewards.flip(0).cumsum(0).flip(0)
    return alive.to(rewards.dtype) * tail_sums


def _discounted_tail_sums(values: torch.Tensor, gamma: Gamma) -> torch.Tensor:
    """R[t] = Σ_{h ≥ t} γ^{h−t} values[h] along dim 0 (backward recursion)."""
    out = torch.empty_like(values)
    factor = gamma.to(values.dtype) if isinstance(gamma, torch.Tensor) else gamma
    running = torch.zeros_like(values[0]) if values.shape[0] else values.new_zeros(())
    for t in range(values.shape[0] - 1, -1, -1):
        running = values[t] + factor * running
        out[t] = running
    return out


def normalize_coefficients(
    coefficients: torch.Tensor,
    alive: torch.Tensor,
    mode: NormalizeName,
    groups: torch.Tensor | None = None,
) -> torch.Tensor:
    """Standardise coefficients over the alive cells: of the whole batch (``"batch"``, per
    agent where ``groups`` says whose each column is) or of each trajectory (``"episode"``):
    (c − mean) / (std + ε), 0 on dead steps. A departure from eq. 5/6, biased for ∇J: the
    mean and std are taken from the samples they rescale, so E[g] is neither ∇J nor a fixed
    multiple of it (README, Estimator options)."""
    if mode == "none":
        return coefficients
    mask = alive.to(coefficients.dtype)
    if mode == "episode" or groups is None:
        dims: tuple[int, ...] = (0, 1) if mode == "batch" else (0,)
        count = mask.sum(dim=dims, keepdim=True).clamp_min(1.0)
        mean = (coefficients * mask).sum(dim=dims, keepdim=True) / count
        spread = ((coefficients - mean) ** 2 * mask).sum(dim=dims, keepdim=True) / count
        return mask * (coefficients - mean) / (spread.sqrt() + NORMALIZE_EPS)
    size = int(groups.max()) + 1

    def per_group(values: torch.Tensor) -> torch.Tensor:
        column_sums = values.sum(dim=0)
        return values.new_zeros(size).index_add_(0, groups, column_sums)

    count = per_group(mask).clamp_min(1.0)
    mean = per_group(coefficients * mask) / count
    centred = coefficients - mean[groups]
    spread = per_group(centred**2 * mask) / count
    return mask * centred / (spread.sqrt()[groups] + NORMALIZE_EPS)


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
    """Dispatch to :func:`reinforce_coefficients` or :func:`gpomdp_coefficients`, then
    :func:`normalize_coefficients`. ``reward_to_go="from_step"`` is GPOMDP's alone (REINFORCE
    has no reward-to-go); config validation rejects the other pairings first. ``groups``:
    each column's agent where the batch holds several agents' trajectories."""
    if estimator == "reinforce":
        if reward_to_go != "from_start":
            raise ValueError("reward_to_go='from_step' needs estimator 'gpomdp'")
        coef = reinforce_coefficients(
            rewards, alive, gamma=gamma, baseline=baseline, weights=weights, groups=groups
        )
    elif estimator == "gpomdp":
        coef = gpomdp_coefficients(
            rewards,
            alive,
            gamma=gamma,
            baseline=baseline,
            weights=weights,
            reward_to_go=reward_to_go,
            groups=groups,
        )
    else:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {estimator!r}")
    return normalize_coefficients(coef, alive, normalize, groups)


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


def clip_rows(gradient: torch.Tensor, max_norm: float | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Scale each row of [A, d] down to norm ``max_norm`` (Assumption 3); returns the rows and
    which were clipped [A]."""
    if max_norm is None:
        return gradient, torch.zeros(gradient.shape[0], dtype=torch.bool, device=gradient.device)
    norms = gradient.double().norm(dim=1)
    clipped = norms > max_norm
    scale = torch.where(clipped, max_norm / norms.clamp_min(1e-300), torch.ones_like(norms))
    return gradient * scale.to(gradient.dtype).unsqueeze(1), clipped


def clip_by_norm(gradient: torch.Tensor, max_norm: float | None) -> tuple[torch.Tensor, bool]:
    """Scale ``gradient`` down to norm ``max_norm`` (Assumption 3); returns (g, was_clipped)."""
    rows, clipped = clip_rows(gradient.unsqueeze(0), max_norm)
    return (rows[0], True) if bool(clipped[0]) else (gradient, False)
