"""Signed-distance stage, NumPy reference engine: triangles in voxels -> signed lattice + brick classes.

Runs the reference stages in order (distance.py, sign.py, farfield.py); the C++ core runs their twins
(csrc/sdf.cpp) and returns the same arrays bit for bit. The sample at a lattice point is
  sign * u            where the exact distance u to the drawn triangles is <= reach (band + 1 voxel),
  sign * max(D, reach) elsewhere (D: the far-field lower bound, capped at 2R),
with the sign from the fill (sign.py). Distances are in voxels.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from navi_compiler.dag.build import brick_reduce
from navi_compiler.gmdag import FLAG_INSIDE_SEEDS, FLAG_LEAK_FALLBACK
from navi_compiler.sdf.distance import brick_classes, make_triangles, nearest_triangles, nondegenerate
from navi_compiler.sdf.farfield import lower_bound, squared_edt, surface_corners
from navi_compiler.sdf.sign import fill, signs, walls

REACH_MARGIN = 1.0  # voxels beyond the band where distances are still exact


@dataclass(frozen=True)
class SdfInput:
    """Geometry in voxel coordinates (see grid.to_voxels)."""

    resolution: int  # R, power of two >= 8
    drawn: np.ndarray  # (F, 3, 3) float64 drawn triangle corners
    face_class: np.ndarray  # (F,) uint8 class id per drawn triangle
    barrier: np.ndarray  # (Fb, 3, 3) float64 barrier triangle corners (block the fill only)
    seeds: np.ndarray  # (S, 3) float64 known-free points
    band: float = 4.0  # voxels kept in bricks


@dataclass(frozen=True)
class SdfResult:
    """The signed lattice and what the fill found."""

    lattice: np.ndarray  # (R+1, R+1, R+1) float32 signed voxels, [x, y, z]
    brick_class: np.ndarray  # (R/8, R/8, R/8) uint8 class per brick (0 for far bricks)
    flags: int  # GMDAG flag bits (inside seeds / leak fallback)
    seeds_used: int  # seeds that started the fill
    wall_points: int  # lattice points within 1/2 voxel of a drawn or barrier triangle
    free_points: int  # lattice points with a positive sign
    stage_seconds: dict[str, float] = field(
        default_factory=dict
    )  # wall time per stage (filled by the C++ engine)


def drop_degenerate(corners: np.ndarray, classes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove zero-area triangles ((T, 3, 3), (T,)): they bound nothing and have no closest-point region."""
    keep = nondegenerate(corners)  # (T,)
    return np.ascontiguousarray(corners[keep]), np.ascontiguousarray(classes[keep])


def stored_bricks(lattice: np.ndarray, band: float) -> np.ndarray:
    """(nb, nb, nb) bool: bricks the DAG stage keeps (not all >= band nor all <= -band)."""
    b32 = np.float32(band)
    return ~((brick_reduce(lattice, np.minimum) >= b32) | (brick_reduce(lattice, np.maximum) <= -b32))


def assemble(
    distance: np.ndarray, lower: np.ndarray, sign: np.ndarray, reach: float, resolution: int
) -> np.ndarray:
    """Exact distances where finite, else max(lower bound capped at 2R, reach); times the sign (float32)."""
    cap = np.float32(2 * resolution)
    far = np.maximum(np.minimum(lower, cap), np.float32(reach))  # float32
    value = np.where(np.isfinite(distance), distance, far)  # float32
    return (value * sign.astype(np.float32)).astype(np.float32)


def signed_field_ref(inp: SdfInput) -> SdfResult:
    """The NumPy reference engine."""
    drawn, classes = drop_degenerate(inp.drawn, inp.face_class)
    barrier, _ = drop_degenerate(inp.barrier, np.zeros(len(inp.barrier), np.uint8))
    tri, bar = make_triangles(drawn), make_triangles(barrier)
    seconds: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(stage: str) -> None:
        now = time.perf_counter()
        seconds[stage] = now - clock[0]
        clock[0] = now

    reach = float(np.float32(inp.band)) + REACH_MARGIN
    near_drawn = nearest_triangles(tri, inp.resolution, reach)
    lap("distance")
    near_barrier = nearest_triangles(bar, inp.resolution, reach)
    lap("barrier")
    wall = walls(near_drawn, near_barrier)  # (R+1)^3 bool
    filled = fill(inp.seeds, wall)
    lap("fill")
    sign = signs(near_drawn, near_barrier, tri, bar, filled)  # (R+1)^3 int8
    lap("sign")
    # distances are measured to drawn and barrier surfaces alike: a barrier (a Quake 3 sky, an open
    # scene's lid) bounds the free space, so the field must reach zero there to stay 1-Lipschitz
    surface = np.minimum(near_drawn.distance, near_barrier.distance)  # (R+1)^3 float32
    sites = surface_corners(surface)  # (R+1)^3 bool
    lap("surface cells")
    lower = lower_bound(squared_edt(sites))  # (R+1)^3 float32
    lap("edt")
    lattice = assemble(surface, lower, sign, reach, inp.resolution)
    lap("assemble")
    brick_class = brick_classes(tri, classes, inp.resolution, stored_bricks(lattice, inp.band))
    lap("classes")
    flags = (FLAG_INSIDE_SEEDS if filled.inside_seeded else 0) | (FLAG_LEAK_FALLBACK if filled.leaked else 0)
    return SdfResult(
        lattice, brick_class, flags, filled.seeds_used, int(wall.sum()), int((sign > 0).sum()), seconds
    )
