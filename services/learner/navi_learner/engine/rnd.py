"""Random Network Distillation on the embedding: a fixed random target and a trained predictor.

The intrinsic reward is the predictor's squared error, normalised by a running estimate of its
standard deviation (kept on the device: no host sync).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from navi_learner.engine.moments import moment_sums, moments_of, pooled_moments


def mlp(dim_in: int, hidden: int, dim_out: int) -> nn.Sequential:
    """Two-layer MLP with a SiLU in between."""
    return nn.Sequential(nn.Linear(dim_in, hidden), nn.SiLU(), nn.Linear(hidden, dim_out))


class RND(nn.Module):
    """Novelty of embeddings (N, D) -> normalised intrinsic reward (N,)."""

    err_mean: torch.Tensor
    err_var: torch.Tensor
    initialised: torch.Tensor

    def __init__(self, embed_dim: int, out_dim: int, momentum: float = 0.01) -> None:
        super().__init__()
        self.target = mlp(embed_dim, 2 * out_dim, out_dim)
        self.target.requires_grad_(False)
        self.predictor = mlp(embed_dim, 2 * out_dim, out_dim)
        self.momentum = momentum
        self.register_buffer("err_mean", torch.zeros(()))  # () float32 running mean of the error
        self.register_buffer("err_var", torch.ones(()))  # () float32 running variance of the error
        self.register_buffer("initialised", torch.zeros((), dtype=torch.bool))  # () bool

    def error(self, emb: torch.Tensor) -> torch.Tensor:
        """Per-sample squared prediction error (N,) on a detached embedding (the encoder is not pushed)."""
        x = emb.detach()  # (N, D)
        return (self.predictor(x) - self.target(x)).pow(2).mean(dim=-1)  # (N,)

    @torch.no_grad()
    def intrinsic(
        self, emb: torch.Tensor, reduce: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> torch.Tensor:
        """Normalised novelty (N,): z-score of the error under running stats (clipped to ±5), updated here.

        `reduce` (data-parallel runs: Sync.sum_) sums a tensor over ranks in place; the running stats
        then follow the batch of every rank's actors, so they stay identical on all ranks."""
        err = self.error(emb)  # (N,)
        if reduce is None:
            mean, var = err.mean(), err.var(unbiased=False)  # () each
        else:
            pooled_mean, pooled_var = pooled_moments(err, reduce)  # () float64 each
            mean, var = pooled_mean.float(), pooled_var.float()  # () float32 each
        self._fold(mean, var)
        return self._score(err)  # (N,)

    @torch.no_grad()
    def intrinsic_pooled(self, emb: torch.Tensor, pooled: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The step of a data-parallel rank whose normaliser folds in sums pooled elsewhere: the running
        stats take in `pooled` (3,) float64 (moment_sums of an earlier batch, summed over ranks), then
        score this batch's error -> (novelty (N,), this batch's moment_sums (3,) float64, to pool). With
        `pooled` what intrinsic's `reduce` returns, both give the same novelty and stats."""
        err = self.error(emb)  # (N,)
        mean, var = moments_of(pooled)  # () float64 each
        self._fold(mean.float(), var.float())
        return self._score(err), moment_sums(err)  # (N,), (3,) float64

    def _fold(self, mean: torch.Tensor, var: torch.Tensor) -> None:
        """Move the running stats toward a batch's mean and variance () (the first batch sets them)."""
        m = torch.where(self.initialised, torch.full_like(mean, self.momentum), torch.ones_like(mean))  # ()
        delta = mean - self.err_mean  # ()
        self.err_mean.add_(m * delta)
        self.err_var.mul_(1 - m).add_(m * (var + (1 - m) * delta.pow(2)))
        self.initialised.fill_(True)

    def _score(self, err: torch.Tensor) -> torch.Tensor:
        """err (N,) as a z-score under the running stats, clipped to ±5 -> (N,)."""
        return ((err - self.err_mean) / (self.err_var.sqrt() + 1e-8)).clamp(-5.0, 5.0)  # (N,)

    def loss(self, emb: torch.Tensor) -> torch.Tensor:
        """Predictor distillation loss, a scalar."""
        return self.error(emb).mean()
