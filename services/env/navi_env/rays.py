"""Ray patterns in the body frame (+X ahead, +Y left, +Z up).

`spherical_directions(az, el)` covers the full sphere: azimuth bin a is centred on yaw angle 2*pi*a/Az
(bin 0 straight ahead along +X, increasing counter-clockwise seen from above, i.e. towards +Y);
elevation bin e is centred on -pi/2 + pi*(e + 0.5)/El (bin 0 looks furthest down, the last furthest
up). Rays are azimuth-major: ray a * El + e, so a (B, Az*El) depth reshapes to (B, Az, El).
"""

from __future__ import annotations

import math

import torch


def spherical_directions(
    azimuth_bins: int = 256, elevation_bins: int = 48, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """(Az * El, 3) float32 unit directions, azimuth-major, as documented in the module."""
    if azimuth_bins < 1 or elevation_bins < 1:
        raise ValueError(f"need at least one bin per axis, got {azimuth_bins} x {elevation_bins}")
    az = torch.arange(azimuth_bins, dtype=torch.float64) * (2.0 * math.pi / azimuth_bins)  # (Az,)
    el = (torch.arange(elevation_bins, dtype=torch.float64) + 0.5) * (math.pi / elevation_bins) - math.pi / 2
    a, e = torch.meshgrid(az, el, indexing="ij")  # (Az, El) each
    dirs = torch.stack(
        [torch.cos(e) * torch.cos(a), torch.cos(e) * torch.sin(a), torch.sin(e)], dim=-1
    )  # (Az, El, 3)
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)  # (Az, El, 3) float64
    return dirs.reshape(-1, 3).to(device=device, dtype=torch.float32)  # (Az*El, 3) float32
