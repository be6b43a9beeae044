"""Dataset adapters: other observation sources -> the canonical DistanceMatrix v2 (N, 3, Az, El).

The policy's input never changes for data; these functions change the data. Every adapter returns
channel 0 = depth / horizon in [0, 1], channel 1 = 0 for a miss and 0.5 + 0.5 * class / 255 for a hit,
channel 2 = channel 0 minus `previous` (the adapter's last output), 0 when no previous frame is given.
Layout (docs/SIMULATION.md): azimuth bin a at 2*pi*a/Az counter-clockwise from straight ahead,
elevation bins from the lowest to the highest elevation of the pattern.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from navi_env.sim.observation import CHANNELS

if TYPE_CHECKING:
    from navi_contracts.models import DistanceMatrix


def _assemble(
    depth: torch.Tensor,
    hit: torch.Tensor,
    class_id: torch.Tensor,
    horizon: float,
    previous: torch.Tensor | None,
) -> torch.Tensor:
    """Stack (N, Az, El) depth meters, hit bool and class ids into (N, 3, Az, El) float32."""
    d = torch.where(hit, depth, horizon).clamp(0.0, horizon) / horizon  # (N, Az, El)
    sem = torch.where(hit, 0.5 + class_id.to(torch.float32).clamp(0, 255) * (0.5 / 255.0), 0.0)  # (N, Az, El)
    delta = torch.zeros_like(d) if previous is None else d - previous[:, 0]  # (N, Az, El)
    return torch.stack((d, sem, delta), dim=1).to(torch.float32)  # (N, 3, Az, El)


def bin_centres(
    azimuth_bins: int, elevation_bins: int, elevation_min_deg: float = -90.0, elevation_max_deg: float = 90.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Azimuth (Az,) and elevation (El,) bin centres, radians, as navi_env.rays lays them out."""
    az = torch.arange(azimuth_bins, dtype=torch.float64) * (2.0 * math.pi / azimuth_bins)  # (Az,)
    lo, hi = math.radians(elevation_min_deg), math.radians(elevation_max_deg)
    el = lo + (torch.arange(elevation_bins, dtype=torch.float64) + 0.5) * (
        (hi - lo) / elevation_bins
    )  # (El,)
    return az, el


def from_equirect_depth(
    depth: torch.Tensor,
    horizon: float,
    azimuth_bins: int,
    elevation_bins: int,
    class_id: torch.Tensor | None = None,
    previous: torch.Tensor | None = None,
) -> torch.Tensor:
    """A 360-degree equirectangular range image (N, H, W) meters -> (N, 3, Az, El).

    Image convention: row 0 is straight up and row H-1 straight down; horizontal image coordinate
    x in [0, W) looks at (x / W - 0.5) * 360 degrees to the viewer's right, so x = W/2 is straight ahead. Pixels that are not finite or are <= 0 or
    >= horizon are misses. Each bin takes the pixel nearest its centre. class_id: (N, H, W) ids or None.
    """
    _, h, w = depth.shape
    az, el = bin_centres(azimuth_bins, elevation_bins)
    # counter-clockwise azimuth a looks at image column W/2 - a * W / (2 pi) (leftward in the image)
    col = torch.remainder(torch.floor(w / 2 - az * (w / (2.0 * math.pi))), w).to(torch.int64)  # (Az,)
    row = ((math.pi / 2 - el) * (h / math.pi)).floor().clamp(0, h - 1).to(torch.int64)  # (El,)
    col, row = col.to(depth.device), row.to(depth.device)
    picked = depth[:, row[None, :], col[:, None]]  # (N, Az, El)
    hit = torch.isfinite(picked) & (picked > 0) & (picked < horizon)  # (N, Az, El)
    cls = (
        torch.zeros_like(picked, dtype=torch.int64)
        if class_id is None
        else class_id[:, row[None, :], col[:, None]]
    )
    return _assemble(torch.nan_to_num(picked, nan=horizon), hit, cls, horizon, previous)


def from_point_cloud(
    points: torch.Tensor,
    valid: torch.Tensor,
    horizon: float,
    azimuth_bins: int,
    elevation_bins: int,
    elevation_min_deg: float = -90.0,
    elevation_max_deg: float = 90.0,
    class_id: torch.Tensor | None = None,
    previous: torch.Tensor | None = None,
) -> torch.Tensor:
    """A LiDAR scan: points (N, P, 3) body frame meters, valid (N, P) bool -> (N, 3, Az, El).

    Each point falls in the bin of its azimuth and elevation; a bin keeps its nearest point (so thin
    obstacles survive down-sampling); bins without points are misses. class_id: (N, P) ids or None.
    """
    n = points.shape[0]
    rng = points.norm(dim=2)  # (N, P)
    azimuth = torch.remainder(torch.atan2(points[..., 1], points[..., 0]), 2.0 * math.pi)  # (N, P)
    elevation = torch.asin((points[..., 2] / rng.clamp_min(1e-9)).clamp(-1.0, 1.0))  # (N, P)
    a = torch.remainder(
        torch.round(azimuth * (azimuth_bins / (2.0 * math.pi))).to(torch.int64), azimuth_bins
    )  # (N, P)
    lo, hi = math.radians(elevation_min_deg), math.radians(elevation_max_deg)
    e = ((elevation - lo) * (elevation_bins / (hi - lo))).floor().to(torch.int64)  # (N, P)
    keep = valid & (rng > 0) & (rng < horizon) & (e >= 0) & (e < elevation_bins)  # (N, P) bool
    cell = (torch.arange(n, device=points.device)[:, None] * azimuth_bins + a) * elevation_bins + e.clamp(
        0, elevation_bins - 1
    )  # (N, P)
    big = torch.full(
        (n * azimuth_bins * elevation_bins,), horizon, dtype=torch.float32, device=points.device
    )  # (N*Az*El,)
    nearest = big.scatter_reduce(0, cell[keep], rng[keep].to(torch.float32), reduce="amin")  # (N*Az*El,)
    depth = nearest.view(n, azimuth_bins, elevation_bins)  # (N, Az, El)
    hit = depth < horizon  # (N, Az, El)
    cls = torch.zeros_like(depth, dtype=torch.int64)  # (N, Az, El)
    if class_id is not None:
        # the class of the point that is the bin's nearest
        winner = keep & (rng.to(torch.float32) <= nearest[cell])  # (N, P) bool
        flat = torch.zeros(
            n * azimuth_bins * elevation_bins, dtype=torch.int64, device=points.device
        )  # (N*Az*El,)
        cls = flat.scatter(0, cell[winner], class_id[winner].to(torch.int64)).view(
            n, azimuth_bins, elevation_bins
        )
    return _assemble(depth, hit, cls, horizon, previous)


def resample(obs: torch.Tensor, azimuth_bins: int, elevation_bins: int) -> torch.Tensor:
    """A DistanceMatrix (N, 3, Az', El') at another resolution -> (N, 3, Az, El), nearest bin centre.

    Both grids span the full sphere; azimuth bin 0 stays straight ahead.
    """
    _, c, az_in, el_in = obs.shape
    if c != CHANNELS:
        raise ValueError(f"expected {CHANNELS} channels, got {c}")
    a = torch.remainder(
        torch.round(torch.arange(azimuth_bins, dtype=torch.float64) * (az_in / azimuth_bins)), az_in
    )  # (Az,)
    e = (
        (torch.arange(elevation_bins, dtype=torch.float64) + 0.5) * (el_in / elevation_bins)
    ).floor()  # (El,)
    a, e = a.to(torch.int64).to(obs.device), e.clamp(0, el_in - 1).to(torch.int64).to(obs.device)
    return obs[:, :, a[:, None], e[None, :]].contiguous()  # (N, 3, Az, El)


def to_contract(
    obs: torch.Tensor, env_ids: torch.Tensor, step_id: int, timestamp: float, run_id: str = ""
) -> DistanceMatrix:
    """(N, 3, Az, El) -> the wire model navi_contracts.DistanceMatrix (copies to the host)."""
    from navi_contracts.models import DistanceMatrix

    host = obs.detach().to("cpu", torch.float32).numpy()  # (N, 3, Az, El)
    return DistanceMatrix(
        env_ids=env_ids.detach().to("cpu", torch.int32).numpy(),
        azimuth_bins=int(obs.shape[2]),
        elevation_bins=int(obs.shape[3]),
        depth=host[:, 0].copy(),
        semantic=host[:, 1].copy(),
        delta_depth=host[:, 2].copy(),
        step_id=step_id,
        timestamp=timestamp,
        run_id=run_id,
    )


def from_contract(msg: DistanceMatrix, device: torch.device | str = "cpu") -> torch.Tensor:
    """The wire model -> (N, 3, Az, El) float32 on `device`."""
    planes = [torch.from_numpy(msg.depth), torch.from_numpy(msg.semantic), torch.from_numpy(msg.delta_depth)]
    return torch.stack(planes, dim=1).to(device=device, dtype=torch.float32)  # (N, 3, Az, El)
