"""Moments of a tensor pooled over the ranks of a data-parallel run (the RND normaliser's and the
advantages' statistics): sums travel through a caller's `reduce`, so this module needs no process group."""

from __future__ import annotations

from collections.abc import Callable

import torch


def pooled_moments(
    x: torch.Tensor, reduce: Callable[[torch.Tensor], torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and population variance () float64 of the union of every rank's x (any shape); `reduce`
    sums a tensor over ranks in place (ppo.dist.Sync.sum_)."""
    v = x.detach().double().reshape(-1)  # (n,) float64
    count = torch.full((), float(v.numel()), dtype=torch.float64, device=x.device)  # () float64
    stats = reduce(torch.stack([v.sum(), v.pow(2).sum(), count]))  # (3,) float64 summed over ranks
    mean = stats[0] / stats[2]  # () float64
    return mean, (stats[1] / stats[2] - mean.pow(2)).clamp(min=0.0)
