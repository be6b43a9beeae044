"""GRU temporal core (cuDNN on CUDA) with episode resets.

The sequence pass splits time at every step where any actor starts an episode (one host read of
the reset pattern per call, during the update only) and runs nn.GRU over each segment, zeroing the
hidden state of the actors that reset at the segment start. The rollout's single step writes the
GRU cell out over nn.GRU's own weights, so it traces into one graph (torch.compile does not trace
nn.GRU) and needs no host read.
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
        g = self.gru
        # the same Parameter objects, outside the nn.GRU (which torch.compile refuses to trace); .to(),
        # load_state_dict and deepcopy keep them the module's own
        names = ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0")
        self.cell_weights = tuple(g.get_parameter(name) for name in names)
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
        h = state[0] * (~resets).to(state[0].dtype)[:, None]  # (N, Hg)
        h = gru_cell(x, h, *self.cell_weights)  # (N, Hg)
        return x + self.out(h), (h,)


def gru_cell(
    x: torch.Tensor,
    h: torch.Tensor,
    w_ih: torch.Tensor,
    w_hh: torch.Tensor,
    b_ih: torch.Tensor,
    b_hh: torch.Tensor,
) -> torch.Tensor:
    """One step of a one-layer nn.GRU, written out: x (N, D), h (N, Hg) -> h' (N, Hg).

    r, z, n stacked in that order in w_ih (3Hg, D) and w_hh (3Hg, Hg), as nn.GRU stores them:
    r = sig(Wir x + Whr h), z = sig(Wiz x + Whz h), n = tanh(Win x + r * (Whn h)), h' = (1 - z) n + z h.
    """
    gi = nn.functional.linear(x, w_ih, b_ih)  # (N, 3Hg)
    gh = nn.functional.linear(h, w_hh, b_hh)  # (N, 3Hg)
    i_r, i_z, i_n = gi.chunk(3, dim=1)  # (N, Hg) each
    h_r, h_z, h_n = gh.chunk(3, dim=1)  # (N, Hg) each
    r = torch.sigmoid(i_r + h_r)  # (N, Hg)
    z = torch.sigmoid(i_z + h_z)  # (N, Hg)
    n = torch.tanh(i_n + r * h_n)  # (N, Hg)
    return (1.0 - z) * n + z * h  # (N, Hg)
