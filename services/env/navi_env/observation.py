"""DistanceMatrix v2: the (N, 3, Az, El) observation and the view statistics the rewards read.

Channels: 0 depth / horizon in [0, 1] (1 = miss); 1 semantic: 0 for a miss, 0.5 + 0.5 * class / 255
for a hit (so any hit reads >= 0.5, class 0 "unknown" reads 0.5); 2 delta depth: channel 0 minus its
value one step earlier, 0 right after a reset. Layout of (Az, El): see navi_env.sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from navi_env.config import RewardConfig

CHANNELS = 3
"""C: depth, semantic, delta depth."""


@dataclass(frozen=True)
class ViewStats:
    """Per-actor statistics of one view, each (N,) float32."""

    void: torch.Tensor  # fraction of rays that missed (saw the horizon)
    near: torch.Tensor  # fraction of rays closer than near_distance
    mid: torch.Tensor  # fraction of rays in [mid_range_min, mid_range_max]
    mid_balance: torch.Tensor  # mid fraction of the left half minus the right half, [-1, 1]


def write_observation(
    obs: torch.Tensor,
    depth: torch.Tensor,
    semantic: torch.Tensor,
    hit: torch.Tensor,
    fresh: torch.Tensor,
    horizon: float,
) -> None:
    """Write obs (N, 3, Az, El) in place from depth (N, R) meters in [0, horizon], the tracer's semantic
    output (N, R) uint8 (0 miss, 1 + class id on a hit) and hit (N, R) bool, which must be semantic > 0.

    `fresh` (N,) bool marks actors whose previous frame belongs to another episode: delta is 0 there.
    Written as few full passes over (N, R) as eager PyTorch allows: this runs every step for every ray.
    """
    n, r = depth.shape
    ch0, ch1, ch2 = obs[:, 0].view(n, r), obs[:, 1].view(n, r), obs[:, 2].view(n, r)  # (N, R) views
    scale = (~fresh).to(depth.dtype).mul_(1.0 / horizon)[:, None]  # (N, 1) 1/horizon, 0 where fresh
    torch.sub(depth, ch0, alpha=horizon, out=ch2)  # depth - horizon * previous
    ch2.mul_(scale)  # depth / horizon - previous, 0 where fresh
    torch.mul(depth, 1.0 / horizon, out=ch0)
    # hit: 0.5 + 0.5 * (semantic - 1) / 255 = semantic * 0.5/255 + (0.5 - 0.5/255) * hit; miss: 0
    torch.mul(semantic, 0.5 / 255.0, out=ch1)
    ch1.add_(hit, alpha=0.5 - 0.5 / 255.0)


def view_stats(depth: torch.Tensor, hit: torch.Tensor, azimuth_bins: int, cfg: RewardConfig) -> ViewStats:
    """Statistics of views: depth (N, R) meters, hit (N, R) bool; rays ordered as navi_env.sensor says.

    Near and mid-range rays are counted by depth (a miss reads the horizon, beyond both bands).
    Left is azimuth bins 1 .. Az/2 - 1 (toward body +Y), right is Az/2 + 1 .. Az - 1.
    """
    n, r = depth.shape
    el = r // azimuth_bins
    half = azimuth_bins // 2
    mid = (depth >= cfg.mid_range_min) & (depth <= cfg.mid_range_max)  # (N, R) bool
    mid_az = mid.view(n, azimuth_bins, el).sum(dim=2, dtype=torch.float32)  # (N, Az) rays per azimuth
    left = mid_az[:, 1:half].sum(dim=1) / ((half - 1) * el)  # (N,)
    right = mid_az[:, half + 1 :].sum(dim=1) / ((azimuth_bins - half - 1) * el)  # (N,)
    return ViewStats(
        void=1.0 - hit.sum(dim=1, dtype=torch.float32) / r,
        near=(depth < cfg.near_distance).sum(dim=1, dtype=torch.float32) / r,
        mid=mid_az.sum(dim=1) / r,
        mid_balance=left - right,
    )
