"""Mamba-2 (SSD) temporal core in pure PyTorch: a chunked scan for sequences, a recurrent step for rollouts.

Per head h the selective state-space recurrence is
    S_t = a_t · S_{t-1} + Δ_t · x_t ⊗ B_t,   a_t = exp(Δ_t · A_h),   y_t = S_t · C_t + D_h · x_t
with S (P × Ns) per head, preceded by a causal depthwise convolution over [x, B, C] and followed by
a SiLU(z) gate, an RMSNorm and the output projection (residual around the whole block).
`resets[t]` zeroes the state (and the convolution window) *before* step t: an episode starts there.
The chunked scan (chunk length L) computes the intra-chunk part as a masked (L × L) matrix product
and carries the state between chunks; a reset inside a chunk masks the decay matrix, so both paths
agree exactly (tests/learner/test_learner_temporal.py).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from navi_learner.config import EngineConfig

CoreState = tuple[torch.Tensor, ...]


def segsum(a: torch.Tensor) -> torch.Tensor:
    """Stable segment sums: a (..., L) -> (..., L, L) with [i, j] = Σ_{k=j+1..i} a_k for i ≥ j, -inf above."""
    length = a.shape[-1]
    x = a[..., :, None].expand(*a.shape, length)  # (..., L_k, L_j)
    strict = torch.tril(torch.ones(length, length, dtype=torch.bool, device=a.device), -1)  # (L, L)
    x = x.masked_fill(~strict, 0.0).cumsum(dim=-2)  # (..., L, L)
    lower = torch.tril(torch.ones(length, length, dtype=torch.bool, device=a.device))  # (L, L)
    return x.masked_fill(~lower, -math.inf)  # (..., L, L)


class Mamba2Core(nn.Module):
    """Mamba-2 block: forward(x (T,N,D), resets (T,N), state) and step(x (N,D), resets (N,), state)."""

    def __init__(self, cfg: EngineConfig) -> None:
        super().__init__()
        d = cfg.embed_dim
        self.inner = cfg.ssm_expand * d
        if self.inner % cfg.ssm_head_dim:
            raise ValueError(
                f"Mamba-2 inner width {self.inner} is not divisible by head dim {cfg.ssm_head_dim}"
            )
        self.heads = self.inner // cfg.ssm_head_dim
        self.head_dim = cfg.ssm_head_dim
        self.d_state = cfg.ssm_state
        self.kernel = cfg.ssm_conv
        self.chunk = cfg.ssm_chunk
        self.conv_dim = self.inner + 2 * self.d_state
        self.norm = nn.RMSNorm(d)
        # Order: [z, x, B, C, dt]
        self.in_proj = nn.Linear(d, 2 * self.inner + 2 * self.d_state + self.heads)
        self.conv_weight = nn.Parameter(
            torch.randn(self.conv_dim, self.kernel) / math.sqrt(self.kernel)
        )  # (Cx, K)
        self.conv_bias = nn.Parameter(torch.zeros(self.conv_dim))  # (Cx,)
        dt = torch.exp(torch.rand(self.heads) * (math.log(0.1) - math.log(1e-3)) + math.log(1e-3))  # (H,)
        self.dt_bias = nn.Parameter(dt + torch.log(-torch.expm1(-dt)))  # (H,) inverse softplus
        self.A_log = nn.Parameter(torch.log(torch.empty(self.heads).uniform_(1.0, 16.0)))  # (H,)
        self.D = nn.Parameter(torch.ones(self.heads))  # (H,)
        self.out_norm = nn.RMSNorm(self.inner)
        self.out_proj = nn.Linear(self.inner, d)

    def initial_state(self, n: int, device: torch.device) -> CoreState:
        """Zero state: SSM (N, H, P, Ns) and convolution window (N, K-1, Cx), float32."""
        ssm = torch.zeros(n, self.heads, self.head_dim, self.d_state, device=device)  # (N, H, P, Ns)
        conv = torch.zeros(n, self.kernel - 1, self.conv_dim, device=device)  # (N, K-1, Cx)
        return (ssm, conv)

    def _split(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        zxbcdt = self.in_proj(self.norm(u))  # (..., 2Di + 2Ns + H)
        z, xbc, dt = torch.split(zxbcdt, [self.inner, self.conv_dim, self.heads], dim=-1)
        return z, xbc, F.softplus(dt + self.dt_bias)  # (..., Di), (..., Cx), (..., H)

    def _finish(self, u: torch.Tensor, y: torch.Tensor, xs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        y = y + self.D[:, None] * xs  # (..., H, P)
        y = y.flatten(-2) * F.silu(z)  # (..., Di)
        return u + self.out_proj(self.out_norm(y))  # (..., D)

    def _conv_seq(
        self, xbc: torch.Tensor, resets: torch.Tensor, conv_state: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Causal depthwise conv over time with episode masking: (T, N, Cx) -> (T, N, Cx), new window."""
        t_len, k = xbc.shape[0], self.kernel
        xp = torch.cat([conv_state.transpose(0, 1), xbc], dim=0)  # (T+K-1, N, Cx)
        rc = torch.cumsum(resets.long(), dim=0)  # (T, N) resets up to and including t
        rcp = torch.cat([rc.new_zeros(k - 1, rc.shape[1]), rc], dim=0)  # (T+K-1, N)
        out = torch.zeros_like(xbc)  # (T, N, Cx)
        for j in range(k):
            same = (rcp[k - 1 - j : k - 1 - j + t_len] == rc).unsqueeze(-1)  # (T, N, 1) same episode
            out = out + xp[k - 1 - j : k - 1 - j + t_len] * same * self.conv_weight[:, k - 1 - j]
        keep = (rcp[-(k - 1) :] == rcp[-1:]).unsqueeze(-1)  # (K-1, N, 1) inputs of the current episode
        new_state = (xp[-(k - 1) :] * keep).transpose(0, 1)  # (N, K-1, Cx)
        return F.silu(out + self.conv_bias), new_state

    def _scan(
        self,
        xs: torch.Tensor,
        dt: torch.Tensor,
        b: torch.Tensor,
        c: torch.Tensor,
        resets: torch.Tensor,
        ssm: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Chunked SSD scan. xs (T,N,H,P), dt (T,N,H), b/c (T,N,Ns), resets (T,N), ssm (N,H,P,Ns)."""
        t_len, n = xs.shape[:2]
        ln = min(self.chunk, t_len)
        pad = (-t_len) % ln
        loga = dt * -torch.exp(self.A_log)  # (T, N, H)
        xdt = xs * dt[..., None]  # (T, N, H, P)
        if pad:
            xdt, loga, b, c = (F.pad(v, [0, 0] * (v.dim() - 1) + [0, pad]) for v in (xdt, loga, b, c))
            resets = F.pad(resets, [0, 0, 0, pad])
        nc = (t_len + pad) // ln

        def chunks(v: torch.Tensor) -> torch.Tensor:
            return v.transpose(0, 1).reshape(n, nc, ln, *v.shape[2:])  # (N, c, L, ...)

        xdt_c, b_c, c_c = chunks(xdt), chunks(b), chunks(c)  # (N,c,L,H,P), (N,c,L,Ns), (N,c,L,Ns)
        a_c = chunks(loga).permute(0, 1, 3, 2)  # (N, c, H, L)
        rc = chunks(resets).long().cumsum(dim=2)  # (N, c, L) resets within the chunk, inclusive
        same = (rc[:, :, :, None] == rc[:, :, None, :]).unsqueeze(2)  # (N, c, 1, L, L)
        decay = torch.exp(segsum(a_c).masked_fill(~same, -math.inf))  # (N, c, H, L, L)
        cb = torch.einsum("ncls,ncts->nclt", c_c, b_c)  # (N, c, L, L)
        y_diag = torch.einsum("nclt,nchlt,ncthp->nclhp", cb, decay, xdt_c)  # (N, c, L, H, P)
        states = torch.einsum("ncht,ncts,ncthp->nchps", decay[:, :, :, -1, :], b_c, xdt_c)  # (N,c,H,P,Ns)
        fresh = (rc == 0).unsqueeze(2)  # (N, c, 1, L) no reset since the chunk start
        in_decay = torch.exp(torch.cumsum(a_c, dim=-1)) * fresh  # (N, c, H, L)
        y_off = []
        for i in range(nc):
            y_off.append(torch.einsum("nls,nhps,nhl->nlhp", c_c[:, i], ssm, in_decay[:, i]))  # (N, L, H, P)
            ssm = in_decay[:, i, :, -1, None, None] * ssm + states[:, i]  # (N, H, P, Ns)
        y = y_diag + torch.stack(y_off, dim=1)  # (N, c, L, H, P)
        y = y.reshape(n, nc * ln, self.heads, self.head_dim).transpose(0, 1)[:t_len]  # (T, N, H, P)
        return y, ssm

    def forward(
        self, x: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[torch.Tensor, CoreState]:
        """Sequence pass: x (T, N, D), resets (T, N) bool -> y (T, N, D), final state."""
        ssm, conv_state = state
        t_len, n = x.shape[:2]
        z, xbc, dt = self._split(x)
        xbc, conv_state = self._conv_seq(xbc, resets, conv_state)  # (T, N, Cx)
        xs, b, c = torch.split(xbc, [self.inner, self.d_state, self.d_state], dim=-1)
        xs = xs.reshape(t_len, n, self.heads, self.head_dim)  # (T, N, H, P)
        y, ssm = self._scan(xs, dt, b, c, resets, ssm)
        return self._finish(x, y, xs, z), (ssm, conv_state)

    def step(self, x: torch.Tensor, resets: torch.Tensor, state: CoreState) -> tuple[torch.Tensor, CoreState]:
        """One recurrent step: x (N, D), resets (N,) bool -> y (N, D), new state."""
        ssm, conv_state = state
        keep = (~resets).to(x.dtype)  # (N,)
        z, xbc, dt = self._split(x)
        window = torch.cat([conv_state * keep[:, None, None], xbc[:, None]], dim=1)  # (N, K, Cx)
        xbc = F.silu((window * self.conv_weight.t()).sum(dim=1) + self.conv_bias)  # (N, Cx)
        xs, b, c = torch.split(xbc, [self.inner, self.d_state, self.d_state], dim=-1)
        xs = xs.reshape(-1, self.heads, self.head_dim)  # (N, H, P)
        a = torch.exp(dt * -torch.exp(self.A_log))  # (N, H)
        ssm = (a * keep[:, None])[..., None, None] * ssm + (dt[..., None] * xs)[..., None] * b[
            :, None, None, :
        ]
        y = torch.einsum("nhps,ns->nhp", ssm, c)  # (N, H, P)
        return self._finish(x, y, xs, z), (ssm, window[:, 1:])
