"""GRU temporal core (cuDNN on CUDA) with episode resets.

The sequence pass splits time at every step where any actor starts an episode (one host read of
the reset pattern per call, during the update only) and runs nn.GRU over each segment, zeroing the
hidden state of the actors that reset at the segment start.
"""

from __future__ import annotations

import itertools

import torch
from torch import nn

from navi_learner.config import EngineConfig
from navi_learner.engine.temporal.mamba2 import CoreState


class GRUCore(nn.Module):
    """forward(x (T,N,D), resets (T,N), state) and step(x (N,D), resets (N,), state); state = (h (N, Hg),)."""

    def __init__(self, cfg: EngineConfig) -> None:
        super().__init__()
        self.hidden = cfg.gru_hidden
        self.gru = nn.GRU(cfg.embed_dim, cfg.gru_hidden)
        self.out = nn.Linear(cfg.gru_hidden, cfg.embed_dim)

    def initial_state(self, n: int, device: torch.device) -> CoreState:
        """Zero hidden state (N, Hg) float32."""
        return (torch.zeros(n, self.hidden, device=device),)  # (N, Hg) float32

    def forward(
        self, x: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[torch.Tensor, CoreState]:
        """Sequence pass: x (T, N, D), resets (T, N) bool -> y (T, N, D), final state."""
        h = state[0][None]  # (1, N, Hg)
        starts = [0, *[t for t in resets.any(dim=1).nonzero().flatten().tolist() if t > 0], x.shape[0]]
        outs = []
        for t0, t1 in itertools.pairwise(starts):
            h = h * (~resets[t0]).to(h.dtype)[None, :, None]  # (1, N, Hg)
            y, h = self.gru(x[t0:t1], h)  # (t1-t0, N, Hg), (1, N, Hg)
            outs.append(y)
        return x + self.out(torch.cat(outs)), (h[0],)  # (T, N, D)

    def step(self, x: torch.Tensor, resets: torch.Tensor, state: CoreState) -> tuple[torch.Tensor, CoreState]:
        """One step: x (N, D), resets (N,) bool -> y (N, D), new state."""
        h = (state[0] * (~resets).to(x.dtype)[:, None])[None]  # (1, N, Hg)
        y, h = self.gru(x[None], h)  # (1, N, Hg), (1, N, Hg)
        return x + self.out(y[0]), (h[0],)
