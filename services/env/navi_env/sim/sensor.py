"""The sensor: the ray pattern in the body frame and the optional range noise and dropout.

Pattern layout (docs/SIMULATION.md): ray r = a * El + e for azimuth bin a and elevation bin e.
Azimuth bin a looks at angle 2*pi*a/Az from body +X toward body +Y (counter-clockwise seen from
above), so bin 0 is straight ahead and bin Az/4 is to the left. Elevation bin e is centred at
lo + (e + 0.5) * (hi - lo) / El, from the lowest (straight down by default) to the highest.
"""

from __future__ import annotations

import math

import torch

from navi_env.sim import rng
from navi_env.sim.config import SensorConfig


def dome_lidar() -> SensorConfig:
    """Preset: a dome LiDAR (360 degrees around, -7 to +52 degrees of elevation, 2 cm range noise,
    1% dropout), like common 360-degree dome scanners on small drones."""
    return SensorConfig(range_noise_std=0.02, dropout=0.01, elevation_min_deg=-7.0, elevation_max_deg=52.0)


def ray_pattern(
    azimuth_bins: int, elevation_bins: int, sensor: SensorConfig, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """Unit ray directions (R, 3) float32 in the body frame, R = Az * El, azimuth-major (see module doc)."""
    az = torch.arange(azimuth_bins, dtype=torch.float64) * (2.0 * math.pi / azimuth_bins)  # (Az,)
    lo, hi = math.radians(sensor.elevation_min_deg), math.radians(sensor.elevation_max_deg)
    el = lo + (torch.arange(elevation_bins, dtype=torch.float64) + 0.5) * (
        (hi - lo) / elevation_bins
    )  # (El,)
    a, e = torch.meshgrid(az, el, indexing="ij")  # (Az, El) each
    dirs = torch.stack(
        (torch.cos(e) * torch.cos(a), torch.cos(e) * torch.sin(a), torch.sin(e)), dim=-1
    )  # (Az, El, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    return dirs.reshape(-1, 3).to(device=device, dtype=torch.float32).contiguous()  # (R, 3)


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
