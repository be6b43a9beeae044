"""Placement stage: fit the scene into the power-of-two cube and move geometry into voxel units.

Both engines share this stage (plain float64 arithmetic), so they see identical voxel coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from navi_compiler.gmdag import BRICK_CELLS, MAX_RESOLUTION


@dataclass(frozen=True)
class Placement:
    """Where the cube sits in the world."""

    resolution: int  # R, cells per edge (power of two)
    origin: tuple[float, float, float]  # min corner, meters
    voxel_size: float  # h, meters


def round_resolution(resolution: int) -> int:
    """The power of two >= `resolution` (at least 8, at most 4096)."""
    if resolution < 1 or resolution > MAX_RESOLUTION:
        raise ValueError(f"resolution {resolution} is outside [1, {MAX_RESOLUTION}]")
    return max(BRICK_CELLS, 1 << (int(resolution) - 1).bit_length())


def place(lo: np.ndarray, hi: np.ndarray, resolution: int, padding: int) -> Placement:
    """Centre the box [lo, hi] ((3,) meters) in a cube of `resolution` (rounded up to a power of two)
    cells with `padding` free cells on each side of its longest axis; the voxel is uniform."""
    r = round_resolution(resolution)
    if not 0 <= 2 * padding < r - 1:
        raise ValueError(f"padding {padding} leaves no room in a {r}^3 cube")
    extent = float((hi - lo).max())
    if not np.isfinite(extent) or extent <= 0.0:
        raise ValueError(f"the scene has no extent (bounds {lo.tolist()}..{hi.tolist()})")
    h = extent / (r - 2 * padding)
    centre = (lo + hi) * 0.5  # (3,) float64
    origin = centre - h * r * 0.5  # (3,) float64
    return Placement(r, (float(origin[0]), float(origin[1]), float(origin[2])), h)


def to_voxels(points: np.ndarray, placement: Placement) -> np.ndarray:
    """World meters (..., 3) -> voxel coordinates (..., 3) float64 (lattice point (i,j,k) at (i,j,k))."""
    return (points - np.array(placement.origin)) / placement.voxel_size
