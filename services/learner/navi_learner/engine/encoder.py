"""RayViTEncoder: DistanceMatrix (N, 3, Az, El) -> embedding (N, D).

Channel 0 (depth / horizon, linear) resolves the near field poorly (a wall at 0.5 m and one at 1 m
differ by 0.005), so the encoder adds a log-depth channel, `near_field`, that spreads it out (1 at
contact, 0.67 at 1% of the horizon, 0 at the horizon). Non-overlapping patches of the four channels
(16 azimuth × 16 elevation rays, 22.5° × 60°: 16×3 = 48 tokens at 256×48) are embedded linearly, a fixed
spherical sin/cos positional encoding (computed once, a buffer, never trained) is added, a few lean
pre-norm transformer blocks mix the tokens (attention by one fused kernel for few tokens on CUDA, by
F.scaled_dot_product_attention, or written out: `EngineConfig.attention`, engine/attention.py), and the
mean token is projected to the embedding.

With `EngineConfig.view_range` below 1 the encoder first caps the view (`cap_view`): whatever lies beyond
that fraction of the horizon reads as an unknown surface at it, so a drone trained in rooms meets the
far walls and sky of a large open map as the near walls it knows. The cap, the near field and the patch
layout are the input stage, engine/tokens.py (one Triton pass on CUDA, from float32 or compact frames).

Ray layout (docs/ACTOR.md): azimuth bin a is at φ = 2π·a/Az (bin 0 straight ahead, increasing to
the left); elevation bin e at θ = -π/2 + π·(e + 0.5)/El (bottom to top).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from navi_learner.config import ATTENTIONS, EngineConfig
from navi_learner.engine.attention import attention_explicit, fused_attention_fits, short_attention
from navi_learner.engine.tokens import CompactFrames, patch_tokens


def spherical_positions(az_patches: int, el_patches: int, dim: int) -> torch.Tensor:
    """Fixed sin/cos encoding of each patch centre's direction on the sphere.

    The first three features are the unit direction vector, then sin/cos of integer multiples of
    the azimuth (periodic over 360°) and of the elevation; zero padding up to D. Returns (Az/p · El/p, D) float32, rows in
    azimuth-major order (the order of `patchify`).
    """
    phi = 2 * math.pi * (torch.arange(az_patches, dtype=torch.float64) + 0.5) / az_patches  # (Pa,)
    theta = (
        -math.pi / 2 + math.pi * (torch.arange(el_patches, dtype=torch.float64) + 0.5) / el_patches
    )  # (Pe,)
    phi_g, theta_g = torch.meshgrid(phi, theta, indexing="ij")  # (Pa, Pe) each
    phi_f, theta_f = phi_g.reshape(-1, 1), theta_g.reshape(-1, 1)  # (P, 1) each
    unit = torch.cat(
        [theta_f.cos() * phi_f.cos(), theta_f.cos() * phi_f.sin(), theta_f.sin()], dim=1
    )  # (P, 3) float64
    k = torch.arange(1, (dim - 3) // 4 + 1, dtype=torch.float64)  # (F,) integer frequencies
    feats = [unit, torch.sin(phi_f * k), torch.cos(phi_f * k), torch.sin(theta_f * k), torch.cos(theta_f * k)]
    pos = torch.cat(feats, dim=1)  # (P, 3 + 4F) with 3 + 4F <= D
    pad = torch.zeros(pos.shape[0], dim - pos.shape[1], dtype=torch.float64)  # (P, rest)
    return torch.cat([pos, pad], dim=1).float()  # (P, D) float32


class Block(nn.Module):
    """Pre-norm transformer block: multi-head attention and a GELU MLP."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int, attention: str = "sdpa") -> None:
        super().__init__()
        if attention not in ATTENTIONS:
            raise ValueError(f"attention must be {' or '.join(ATTENTIONS)}, got {attention!r}")
        self.attend = attention_explicit if attention == "explicit" else F.scaled_dot_product_attention
        self.fused = attention == "fused"  # short_attention on the qkv layout itself
        self.fused_on_cuda = attention == "auto"  # short_attention on CUDA, sdpa elsewhere
        self.heads = heads
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.fc1 = nn.Linear(dim, mlp_ratio * dim)
        self.fc2 = nn.Linear(mlp_ratio * dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, p, d = x.shape
        qkv = self.qkv(self.norm1(x)).view(n, p, 3, self.heads, d // self.heads)  # (N, P, 3, h, D/h)
        if self.fused or (self.fused_on_cuda and qkv.is_cuda):
            att = short_attention(qkv)  # (N, P, h, D/h)
        else:
            q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)  # (N, h, P, D/h) each
            att = self.attend(q, k, v).transpose(1, 2)  # (N, P, h, D/h)
        x = x + self.proj(att.reshape(n, p, d))  # (N, P, D)
        return x + self.fc2(F.gelu(self.fc1(self.norm2(x))))  # (N, P, D)


class RayViTEncoder(nn.Module):
    """DistanceMatrix (N, 3, Az, El) float -> embedding (N, D) float32."""

    pos: torch.Tensor

    def __init__(self, obs_shape: tuple[int, int, int], cfg: EngineConfig) -> None:
        super().__init__()
        c, az, el = obs_shape
        pa, pe = cfg.patch_for(az, el)
        self.patch = (pa, pe)
        self.embed = nn.Linear((c + 1) * pa * pe, cfg.embed_dim)  # the channels and near_field
        self.register_buffer(
            "pos", spherical_positions(az // pa, el // pe, cfg.embed_dim), persistent=False
        )  # (P, D) float32
        why = fused_attention_fits((az // pa) * (el // pe), cfg.embed_dim // cfg.encoder_heads)
        if cfg.attention == "fused" and why is not None:
            raise ValueError(f"attention fused cannot take this encoder: {why}; use sdpa or auto")
        # the blocks' attention: cfg.attention, where auto becomes sdpa if the fused kernel cannot serve
        self.attention = "sdpa" if cfg.attention == "auto" and why is not None else cfg.attention
        self.blocks = nn.ModuleList(
            Block(cfg.embed_dim, cfg.encoder_heads, cfg.mlp_ratio, self.attention)
            for _ in range(cfg.encoder_layers)
        )
        self.norm = nn.LayerNorm(cfg.embed_dim)
        self.out = nn.Linear(cfg.embed_dim, cfg.embed_dim)
        self.view_range = float(torch.tensor(cfg.view_range, dtype=torch.float16))  # a float16 depth value

    @property
    def n_tokens(self) -> int:
        """Number of patch tokens P."""
        return int(self.pos.shape[0])

    def forward(self, obs: torch.Tensor | CompactFrames, dtype: torch.dtype | None = None) -> torch.Tensor:
        """obs (N, 3, Az, El) float32 frames, or a compact minibatch (L steps of M sequences, N = L·M) ->
        embedding (N, D) float32. `dtype`: what the patch embedding multiplies in (bf16 under amp; None,
        its weight's dtype)."""
        tokens = patch_tokens(
            obs, self.patch, self.view_range, dtype or self.embed.weight.dtype
        )  # (N, P, 4·pa·pe)
        x = self.embed(tokens) + self.pos  # (N, P, D)
        for block in self.blocks:
            x = block(x)  # (N, P, D)
        return self.out(self.norm(x.mean(dim=1))).float()  # (N, D) float32
