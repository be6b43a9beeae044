"""ActorCriticHeads: a 4-DOF Gaussian policy over [forward, vertical, lateral, yaw_rate] and a value V(s).

The Gaussian is tanh-free with a state-independent log standard deviation; the environment clips
actions to [-1, 1]. The log-probability and entropy are written out (no torch.distributions objects
on the hot path).
"""

from __future__ import annotations

import math

import torch
from torch import nn

ACTION_DIM = 4
LOG_2PI = math.log(2 * math.pi)


def gaussian_log_prob(actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """Log density of a diagonal Gaussian: actions/mean (..., A), log_std (A,) -> (...,)."""
    z = (actions - mean) * torch.exp(-log_std)  # (..., A)
    return (-0.5 * z.pow(2) - log_std - 0.5 * LOG_2PI).sum(dim=-1)  # (...,)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian with log_std (A,): a scalar."""
    return (log_std + 0.5 * (1.0 + LOG_2PI)).sum()


class ActorCriticHeads(nn.Module):
    """Features (..., D) -> action mean (..., 4) and value (...,); log_std is a learned (4,) vector."""

    def __init__(self, dim: int, hidden: int, init_log_std: float) -> None:
        super().__init__()
        mean_out, value_out = nn.Linear(hidden, ACTION_DIM), nn.Linear(hidden, 1)
        nn.init.orthogonal_(mean_out.weight, gain=0.01)
        nn.init.zeros_(mean_out.bias)
        nn.init.orthogonal_(value_out.weight, gain=1.0)
        nn.init.zeros_(value_out.bias)
        self.actor = nn.Sequential(nn.Linear(dim, hidden), nn.SiLU(), mean_out)
        self.critic = nn.Sequential(nn.Linear(dim, hidden), nn.SiLU(), value_out)
        self.log_std = nn.Parameter(torch.full((ACTION_DIM,), init_log_std))  # (4,)

    def forward(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.actor(feat), self.critic(feat).squeeze(-1)  # (..., 4), (...,)
