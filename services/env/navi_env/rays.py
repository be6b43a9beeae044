"""Ray patterns in the body frame (+X ahead, +Y left, +Z up), and the tiled order the tracer runs them in.

`ray_pattern(az, el, sensor)` is the sensor's pattern: ray r = a * El + e for azimuth bin a and
elevation bin e (docs/SIMULATION.md). Azimuth bin a looks at angle 2*pi*a/Az from body +X toward
body +Y (counter-clockwise seen from above), so bin 0 is straight ahead and bin Az/4 is to the left.
Elevation bin e is centred at lo + (e + 0.5) * (hi - lo) / El, from the sensor's lowest elevation
(straight down by default) to its highest.

`spherical_directions(az, el)` covers the full sphere: azimuth bin a is centred on yaw angle 2*pi*a/Az
(bin 0 straight ahead along +X, increasing counter-clockwise seen from above, i.e. towards +Y);
elevation bin e is centred on -pi/2 + pi*(e + 0.5)/El (bin 0 looks furthest down, the last furthest
up). Rays are azimuth-major: ray a * El + e, so a (B, Az*El) depth reshapes to (B, Az, El).
"""

from __future__ import annotations

import math

import torch

from navi_env.config import SensorConfig


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


def tiled_ray_order(
    azimuth_bins: int = 256, elevation_bins: int = 48, tile_azimuth: int = 16, tile_elevation: int = 2
) -> torch.Tensor:
    """(Az * El,) int32 permutation of the azimuth-major pattern that groups rays in tiles of
    tile_azimuth x tile_elevation neighbouring directions, tile after tile.

    Passed as `trace(..., ray_order=...)` it puts one tile in one GPU warp (32 rays for 16 x 2), so the
    rays of a warp take similar step counts; the outputs keep the azimuth-major layout.
    """
    if azimuth_bins % tile_azimuth or elevation_bins % tile_elevation:
        raise ValueError(
            f"{azimuth_bins}x{elevation_bins} bins do not split into {tile_azimuth}x{tile_elevation} tiles"
        )
    idx = torch.arange(azimuth_bins * elevation_bins, dtype=torch.int32)  # (Az*El,) ray ids
    tiles = idx.view(
        azimuth_bins // tile_azimuth, tile_azimuth, elevation_bins // tile_elevation, tile_elevation
    )
    return tiles.permute(0, 2, 1, 3).reshape(-1).contiguous()  # (Az*El,) int32


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
