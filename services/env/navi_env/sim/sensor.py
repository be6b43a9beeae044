"""The sensor's range noise and dropout over exact traced depths, and the dome LiDAR preset.

The ray pattern itself is navi_env.rays.ray_pattern.
"""

from __future__ import annotations

import torch

from navi_env.config import SensorConfig
from navi_env.sim import rng


def dome_lidar() -> SensorConfig:
    """Preset: a dome LiDAR (360 degrees around, -7 to +52 degrees of elevation, 2 cm range noise,
    1% dropout), like common 360-degree dome scanners on small drones."""
    return SensorConfig(range_noise_std=0.02, dropout=0.01, elevation_min_deg=-7.0, elevation_max_deg=52.0)


def apply_sensor(
    depth: torch.Tensor,
    semantic: torch.Tensor,
    sensor: SensorConfig,
    horizon: float,
    seed: torch.Tensor,
    tick: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy depth (N, R) and semantic (N, R) from exact ones (semantic 0 = miss): Gaussian range noise
    on hits (std range_noise_std + range_noise_relative * depth, clipped to [0, horizon]) and dropout
    (a dropped ray reads as a miss: the horizon and semantic 0). Identical on CPU and CUDA for the same
    seed and tick (0-d int64 tensors)."""
    n, r = depth.shape
    hit = semantic > 0  # (N, R) bool
    index = torch.arange(n * r, device=depth.device, dtype=torch.int64).reshape(n, r)  # (N, R)
    if sensor.range_noise_std > 0.0 or sensor.range_noise_relative > 0.0:
        std = sensor.range_noise_std + sensor.range_noise_relative * depth  # (N, R)
        noisy = depth + std * rng.normal(seed, rng.STREAM_NOISE, tick, index)  # (N, R)
        depth = torch.where(hit, noisy.clamp(0.0, horizon), depth)
    if sensor.dropout > 0.0:
        dropped = rng.uniform(seed, rng.STREAM_DROPOUT, tick, index) < sensor.dropout  # (N, R) bool
        depth = torch.where(dropped, horizon, depth)
        semantic = semantic * ~dropped
    return depth, semantic
