"""Sign stage (NumPy reference; csrc/sign.h is the C++ twin): which lattice points are free.

- Walls: a lattice point within WALL (= 1/2 voxel) of a drawn or barrier triangle. Every lattice edge
  that crosses a triangle has such an endpoint, so a 6-connected fill through non-wall points never
  steps through a surface, however thin.
- Fill: from the non-wall corner nearest each seed (corners of the seed's cell in order of distance,
  ties by corner number c = x | y<<1 | z<<2), or, with no usable seed, from every non-wall point on
  the cube's border. Reached points are free (+), other non-wall points solid (-).
- Leak: seeded from inside, a fill that reaches the border leaked; the stage warns (the caller logs
  it), sets the leak flag and fills from the border instead.
- A wall point p takes its sign from probes: with q the closest point on its nearest drawn triangle
  (nearest barrier triangle when only a barrier makes it a wall) and u = |p - q|, the lattice points
  nearest q + PROBE * (p - q) / u ("mine") and q - PROBE * (p - q) / u ("other") are looked up.
  + when mine is reached and other is not (the free side of a one-sided surface); - otherwise (inside
  solid, or a thin two-sided wall: free on both sides, so the tracer sees a sign change). Barriers take
  the same rule as drawn walls: a barrier the drone cannot pass with free space on both sides (a sky
  pane between two rooms, a thin solid nodraw brush) is seen by the rays as the wall it is. u == 0
  gives -.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from navi_compiler.sdf.distance import Nearest, Triangles, closest_points

WALL = 0.5  # voxels
PROBE = 1.5  # voxels from the surface, just outside the blocked shell


@dataclass(frozen=True)
class Fill:
    """Outcome of the inside/outside flood fill."""

    reached: np.ndarray  # (R+1, R+1, R+1) bool: free non-wall points
    inside_seeded: bool  # the fill started from seeds (and did not leak)
    leaked: bool  # seeded from inside, reached the border, fell back to the border
    seeds_used: int  # seeds that found a non-wall start point


def seed_starts(seeds: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """Seeds (S, 3) voxels -> (K, 3) int64 start points (one per usable seed, in seed order)."""
    r = wall.shape[0] - 1
    starts: list[np.ndarray] = []
    corners = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)  # (8, 3)
    for s in seeds:
        if not ((s >= 0.0) & (s <= float(r))).all():
            continue
        base = np.minimum(np.floor(s).astype(np.int64), r - 1)  # (3,)
        pts = base + corners  # (8, 3)
        diff = pts - s  # (8, 3) float64
        d2 = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2]  # (8,)
        for c in np.lexsort((np.arange(8), d2)):
            if not wall[tuple(pts[c])]:
                starts.append(pts[c])
                break
    return np.array(starts, np.int64).reshape(-1, 3)


def border(n: int) -> np.ndarray:
    """(n, n, n) bool: the lattice points on the cube's faces."""
    out = np.zeros((n, n, n), bool)  # (n, n, n) bool
    out[[0, -1], :, :] = True
    out[:, [0, -1], :] = True
    out[:, :, [0, -1]] = True
    return out


def flood(start: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """6-connected fill of non-wall points from `start` ((n, n, n) bool), by repeated dilation."""
    reached = start & ~wall
    frontier = reached.copy()
    while frontier.any():
        grown = np.zeros_like(frontier)  # (n, n, n) bool
        grown[1:] |= frontier[:-1]
        grown[:-1] |= frontier[1:]
        grown[:, 1:] |= frontier[:, :-1]
        grown[:, :-1] |= frontier[:, 1:]
        grown[:, :, 1:] |= frontier[:, :, :-1]
        grown[:, :, :-1] |= frontier[:, :, 1:]
        frontier = grown & ~wall & ~reached
        reached |= frontier
    return reached


def fill(seeds: np.ndarray, wall: np.ndarray) -> Fill:
    """Flood fill from the seeds (voxels, (S, 3)), with leak detection and the border fallback."""
    n = wall.shape[0]
    edge = border(n)
    starts = seed_starts(seeds, wall)  # (K, 3)
    if len(starts):
        start = np.zeros((n, n, n), bool)  # (n, n, n) bool
        start[starts[:, 0], starts[:, 1], starts[:, 2]] = True
        reached = flood(start, wall)
        if not (reached & edge).any():
            return Fill(reached, True, False, len(starts))
        return Fill(flood(edge, wall), False, True, len(starts))
    return Fill(flood(edge, wall), False, False, 0)


def _probe_reached(points: np.ndarray, reached: np.ndarray) -> np.ndarray:
    """Reached state of the lattice point nearest each probe ((P, 3) voxels; floor(x + 0.5), clamped)."""
    r = reached.shape[0] - 1
    idx = np.clip(np.floor(points + 0.5), 0, r).astype(np.int64)  # (P, 3)
    return reached[idx[:, 0], idx[:, 1], idx[:, 2]]


def _probes(pts: np.ndarray, tri: Triangles, near: np.ndarray, reached: np.ndarray) -> tuple[np.ndarray, ...]:
    """For wall points pts (P, 3) with nearest triangles near (P,): (mine, other, u > 0), each (P,) bool."""
    q = closest_points(pts, tri, near)  # (P, 3)
    d = pts - q  # (P, 3)
    u = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])  # (P,)
    off = u > 0.0  # (P,)
    with np.errstate(divide="ignore", invalid="ignore"):
        step = np.where(off[:, None], d * (PROBE / u)[:, None], 0.0)  # (P, 3)
    return _probe_reached(q + step, reached), _probe_reached(q - step, reached), off


def walls(drawn: Nearest, barrier: Nearest) -> np.ndarray:
    """(R+1)^3 bool: points whose float32 distance to a drawn or barrier triangle is <= WALL."""
    return (drawn.distance <= np.float32(WALL)) | (barrier.distance <= np.float32(WALL))


def signs(drawn: Nearest, barrier: Nearest, tri: Triangles, bar: Triangles, filled: Fill) -> np.ndarray:
    """+1 / -1 per lattice point ((R+1)^3 int8) following the rules in the module docstring."""
    drawn_wall = drawn.distance <= np.float32(WALL)
    barrier_wall = (barrier.distance <= np.float32(WALL)) & ~drawn_wall
    out = np.where(filled.reached, 1, -1).astype(np.int8)  # (R+1, R+1, R+1) int8
    pts = np.argwhere(drawn_wall)  # (P, 3)
    if len(pts):
        mine, other, off = _probes(pts.astype(np.float64), tri, drawn.triangle[drawn_wall], filled.reached)
        out[drawn_wall] = np.where(mine & ~other & off, 1, -1)
    pts = np.argwhere(barrier_wall)  # (P, 3)
    if len(pts):
        mine, other, off = _probes(
            pts.astype(np.float64), bar, barrier.triangle[barrier_wall], filled.reached
        )
        out[barrier_wall] = np.where(mine & ~other & off, 1, -1)
    return out
