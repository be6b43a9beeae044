"""PPO losses as pure functions: `ppo_loss(...) -> (loss, metrics)`; metrics stay on the device."""

from __future__ import annotations

import torch


def normalize(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Zero-mean, unit-std copy of x (any shape)."""
    return (x - x.mean()) / (x.std(unbiased=False) + eps)


def ppo_loss(
    new_logp: torch.Tensor,
    old_logp: torch.Tensor,
    advantages: torch.Tensor,
    new_values: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
    entropy: torch.Tensor,
    *,
    clip_coef: float,
    value_clip_coef: float,
    vf_coef: float,
    ent_coef: float,
    norm_adv: bool,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Clipped PPO objective.

    new_logp, old_logp, advantages, new_values, old_values, returns: float32 of one shape (e.g. (T, N));
    entropy: a float32 scalar or the same shape. Returns the scalar loss
    `policy_loss + vf_coef·value_loss − ent_coef·entropy` and detached metrics: policy_loss,
    value_loss, entropy, approx_kl (the (r−1)−log r estimator), clipfrac.
    """
    adv = normalize(advantages) if norm_adv else advantages
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip_coef, 1 + clip_coef)).mean()
    v_unclipped = (new_values - returns).pow(2)
    if value_clip_coef > 0:
        v_clipped = old_values + (new_values - old_values).clamp(-value_clip_coef, value_clip_coef)
        v_loss = 0.5 * torch.max(v_unclipped, (v_clipped - returns).pow(2)).mean()
    else:
        v_loss = 0.5 * v_unclipped.mean()
    ent = entropy.mean()
    loss = pg_loss + vf_coef * v_loss - ent_coef * ent
    with torch.no_grad():
        metrics = {
            "policy_loss": pg_loss.detach(),
            "value_loss": v_loss.detach(),
            "entropy": ent.detach(),
            "approx_kl": ((ratio - 1) - log_ratio).mean(),
            "clipfrac": ((ratio - 1).abs() > clip_coef).float().mean(),
        }
    return loss, metrics


def mean_bound_loss(mean: torch.Tensor, bound: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Penalty on action means beyond ±bound: mean (..., A) -> (Σ_a relu(|μ_a| − bound)² averaged over the
    samples (), the share of mean entries outside the bound () detached). Zero inside the bound, its
    gradient pulls each mean outside back towards it."""
    excess = (mean.abs() - bound).clamp(min=0.0)  # (..., A)
    loss = excess.pow(2).sum(dim=-1).mean()  # ()
    return loss, (excess > 0).float().mean().detach()
