"""Moments of a tensor pooled over the ranks of a data-parallel run (the RND normaliser's and the
advantages' statistics): sums travel through a caller's `reduce`, so this module needs no process group."""

from __future__ import annotations

from collections.abc import Callable

import torch


def moment_sums(x: torch.Tensor) -> torch.Tensor:
    """(3,) float64: the sum, the sum of squares and the count of x's elements (any shape), the
    statistics that pool over ranks by summing."""
    v = x.detach().double().reshape(-1)  # (n,) float64
    count = torch.full((), float(v.numel()), dtype=torch.float64, device=x.device)  # () float64
    return torch.stack([v.sum(), v.pow(2).sum(), count])  # (3,) float64


def moments_of(sums: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and population variance (...) float64 of the elements whose moment_sums, summed over ranks,
    are `sums` (..., 3): () each for one set of sums, (K,) each for K."""
    mean = sums[..., 0] / sums[..., 2]  # (...) float64
    return mean, (sums[..., 1] / sums[..., 2] - mean.pow(2)).clamp(min=0.0)


def pooled_moments(
    x: torch.Tensor, reduce: Callable[[torch.Tensor], torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and population variance () float64 of the union of every rank's x (any shape); `reduce`
    sums a tensor over ranks in place (ppo.dist.Sync.sum_)."""
    return moments_of(reduce(moment_sums(x)))  # the (3,) sums over every rank
