"""Plain sequential Mamba-2 reference ("mambapy"): the same parameters as Mamba2Core, one step at a time.

Written as directly as possible (explicit convolution window, explicit per-step state update), it is
the slow, obviously correct twin of the chunked scan and a selectable `--temporal-core` for debugging.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from navi_learner.engine.temporal.mamba2 import CoreState, Mamba2Core


class MambaPyCore(Mamba2Core):
    """Mamba-2 evaluated by a Python loop over time (no chunking, no fused einsums)."""

    def _plain_step(
        self, x: torch.Tensor, reset: torch.Tensor, ssm: torch.Tensor, window: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (N, D), reset (N,), ssm (N, H, P, Ns), window (N, K-1, Cx) -> y (N, D), ssm, window."""
        keep = (~reset).to(x.dtype)[:, None]  # (N, 1)
        ssm = ssm * keep[:, :, None, None]
        window = window * keep[:, :, None]
        zxbcdt = self.in_proj(self.norm(x))  # (N, 2Di + 2Ns + H)
        z = zxbcdt[:, : self.inner]  # (N, Di)
        xbc = zxbcdt[:, self.inner : self.inner + self.conv_dim]  # (N, Cx)
        dt = F.softplus(zxbcdt[:, self.inner + self.conv_dim :] + self.dt_bias)  # (N, H)
        taps = [window[:, i] for i in range(self.kernel - 1)] + [xbc]  # K x (N, Cx), oldest first
        conv = self.conv_bias.expand_as(xbc).clone()  # (N, Cx)
        for i, tap in enumerate(taps):
            conv = conv + tap * self.conv_weight[:, i]
        conv = F.silu(conv)  # (N, Cx)
        xs = conv[:, : self.inner].reshape(-1, self.heads, self.head_dim)  # (N, H, P)
        b = conv[:, self.inner : self.inner + self.d_state]  # (N, Ns)
        c = conv[:, self.inner + self.d_state :]  # (N, Ns)
        a = torch.exp(-torch.exp(self.A_log) * dt)  # (N, H)
        outer = xs[:, :, :, None] * b[:, None, None, :]  # (N, H, P, Ns)
        ssm = a[:, :, None, None] * ssm + dt[:, :, None, None] * outer  # (N, H, P, Ns)
        y = (ssm * c[:, None, None, :]).sum(dim=-1)  # (N, H, P)
        new_window = torch.stack(taps[1:], dim=1)  # (N, K-1, Cx)
        return self._finish(x, y, xs, z), ssm, new_window

    def forward(
        self, x: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[torch.Tensor, CoreState]:
        """Sequence pass by a loop over time: x (T, N, D), resets (T, N) -> y (T, N, D), state."""
        ssm, window = state
        ys = []
        for t in range(x.shape[0]):
            y, ssm, window = self._plain_step(x[t], resets[t], ssm, window)
            ys.append(y)
        return torch.stack(ys), (ssm, window)  # (T, N, D)

    def step(self, x: torch.Tensor, resets: torch.Tensor, state: CoreState) -> tuple[torch.Tensor, CoreState]:
        """One step: x (N, D), resets (N,) -> y (N, D), state."""
        y, ssm, window = self._plain_step(x, resets, state[0], state[1])
        return y, (ssm, window)
