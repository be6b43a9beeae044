"""Distance stage (NumPy reference; csrc/distance.h is the C++ twin): exact point-to-triangle distances
on the lattice points near the triangles, and the semantic class of each brick.

All coordinates are voxels (lattice point (i, j, k) at (i, j, k)), float64. Every formula is written
in the same operation order as the C++ twin so both produce bit-identical results:
- `closest_points` is Ericson's Voronoi-region closest point on a triangle ("Real-Time Collision
  Detection", 5.1.5); squared distance = dx*dx + dy*dy + dz*dz.
- A lattice point's distance is exact when it is <= `reach` (compared in float64, stored as float32);
  the nearest triangle is the one with the smallest squared distance, ties to the lowest triangle
  index. Points farther than `reach` from every triangle get +inf (the far-field stage bounds them).
- Work is split by brick: a brick's candidates are the triangles whose bounding box meets the brick's
  box grown by `reach`; a brick computes the points it owns (local index 0..7 per axis, 0..8 on the
  cube's last brick), so every lattice point is computed exactly once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from navi_compiler.gmdag import BRICK_CELLS

CLASS_REACH = 12.0  # voxels: a brick's class comes from the nearest drawn triangle within this of its centre


@dataclass(frozen=True)
class Triangles:
    """Triangles in voxel coordinates with their precomputed edges."""

    a: np.ndarray  # (T, 3) float64 first corner
    b: np.ndarray  # (T, 3) float64
    c: np.ndarray  # (T, 3) float64
    ab: np.ndarray  # (T, 3) float64 b - a
    ac: np.ndarray  # (T, 3) float64 c - a
    bc: np.ndarray  # (T, 3) float64 c - b
    lo: np.ndarray  # (T, 3) float64 bounding box min
    hi: np.ndarray  # (T, 3) float64 bounding box max


def make_triangles(corners: np.ndarray) -> Triangles:
    """(T, 3, 3) float64 corners in voxels -> Triangles (degenerate ones are the caller's to drop)."""
    a, b, c = (np.ascontiguousarray(corners[:, i]) for i in range(3))  # (T, 3) each
    return Triangles(
        a, b, c, b - a, c - a, c - b, np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
    )


def nondegenerate(corners: np.ndarray) -> np.ndarray:
    """(T, 3, 3) corners -> (T,) bool: the triangle has a non-zero cross product (exactly)."""
    ab = corners[:, 1] - corners[:, 0]  # (T, 3)
    ac = corners[:, 2] - corners[:, 0]  # (T, 3)
    nx = ab[:, 1] * ac[:, 2] - ab[:, 2] * ac[:, 1]
    ny = ab[:, 2] * ac[:, 0] - ab[:, 0] * ac[:, 2]
    nz = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    return (nx != 0.0) | (ny != 0.0) | (nz != 0.0)


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def closest_points(p: np.ndarray, tri: Triangles, idx: np.ndarray) -> np.ndarray:
    """Closest point on triangle idx[...] to p[...] (broadcast shapes (..., 3) and (...)): (..., 3)."""
    a, b, c = tri.a[idx], tri.b[idx], tri.c[idx]  # (..., 3)
    ab, ac, bc = tri.ab[idx], tri.ac[idx], tri.bc[idx]  # (..., 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        ap, bp, cp = p - a, p - b, p - c  # (..., 3)
        d1, d2 = _dot(ab, ap), _dot(ac, ap)
        d3, d4 = _dot(ab, bp), _dot(ac, bp)
        d5, d6 = _dot(ab, cp), _dot(ac, cp)
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        in_a = (d1 <= 0) & (d2 <= 0)
        in_b = (d3 >= 0) & (d4 <= d3)
        in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        in_c = (d6 >= 0) & (d5 <= d6)
        in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        in_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = 1.0 / (va + vb + vc)
        v_in, w_in = vb * denom, vc * denom
        q_ab = a + v_ab[..., None] * ab
        q_ac = a + w_ac[..., None] * ac
        q_bc = b + w_bc[..., None] * bc
        q_in = a + ab * v_in[..., None] + ac * w_in[..., None]
    conds = [in_a, in_b, in_ab, in_c, in_ac, in_bc]
    choices = [a, b, q_ab, c, q_ac, q_bc]
    out = q_in
    for cond, q in zip(reversed(conds), reversed(choices), strict=True):
        out = np.where(cond[..., None], q, out)  # (..., 3) float64
    return out


def squared_distances(p: np.ndarray, tri: Triangles, idx: np.ndarray) -> np.ndarray:
    """|p - closest point|^2 as dx*dx + dy*dy + dz*dz, broadcast like `closest_points`."""
    d = p - closest_points(p, tri, idx)  # (..., 3)
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def brick_candidates(tri: Triangles, n_bricks: int, reach: float) -> dict[int, np.ndarray]:
    """Brick flat index (bx*nb*nb + by*nb + bz) -> ascending triangle indices whose bounding box meets
    the brick's box [8b, 8b+8] grown by `reach`. Only bricks with candidates appear."""
    lo = np.clip(np.ceil((tri.lo - BRICK_CELLS - reach) / BRICK_CELLS), 0, n_bricks - 1).astype(
        np.int64
    )  # (T, 3)
    hi = np.clip(np.floor((tri.hi + reach) / BRICK_CELLS), 0, n_bricks - 1).astype(np.int64)  # (T, 3)
    hit = (tri.hi + reach >= 0).all(axis=1) & (tri.lo - reach <= n_bricks * BRICK_CELLS).all(axis=1)  # (T,)
    pairs: list[np.ndarray] = []
    for t in np.flatnonzero(hit & (lo <= hi).all(axis=1)):
        gx, gy, gz = np.meshgrid(*[np.arange(lo[t, k], hi[t, k] + 1) for k in range(3)], indexing="ij")
        flat = (gx * n_bricks + gy) * n_bricks + gz  # bricks covered by triangle t
        pairs.append(np.stack([flat.ravel(), np.full(flat.size, t)], axis=1))
    if not pairs:
        return {}
    all_pairs = np.concatenate(pairs)  # (P, 2) [brick, triangle]
    order = np.lexsort((all_pairs[:, 1], all_pairs[:, 0]))
    all_pairs = all_pairs[order]
    bricks, starts = np.unique(all_pairs[:, 0], return_index=True)  # (U,), (U,)
    ends = np.append(starts[1:], len(all_pairs))
    return {int(b): all_pairs[s:e, 1] for b, s, e in zip(bricks, starts, ends, strict=True)}


def owned_points(brick: int, n_bricks: int) -> np.ndarray:
    """Lattice points a brick computes: (P, 3) int64 (local 0..7 per axis, 0..8 on the last brick)."""
    bx, by, bz = brick // (n_bricks * n_bricks), (brick // n_bricks) % n_bricks, brick % n_bricks
    axes = [
        np.arange(BRICK_CELLS * b, BRICK_CELLS * b + BRICK_CELLS + (1 if b == n_bricks - 1 else 0))
        for b in (bx, by, bz)
    ]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)


@dataclass(frozen=True)
class Nearest:
    """Unsigned distance to the nearest triangle on every lattice point, where it is <= reach."""

    distance: (
        np.ndarray
    )  # (R+1, R+1, R+1) float32 voxels (float32 of the float64 distance), +inf beyond reach
    triangle: np.ndarray  # (R+1, R+1, R+1) int32 nearest triangle index, -1 beyond reach


def nearest_triangles(tri: Triangles, resolution: int, reach: float) -> Nearest:
    """Exact distances within `reach` of the triangles (the slow, obviously correct twin)."""
    n = resolution + 1
    nb = resolution // BRICK_CELLS
    dist = np.full((n, n, n), np.inf, np.float32)  # (R+1, R+1, R+1) float32
    near = np.full((n, n, n), -1, np.int32)  # (R+1, R+1, R+1) int32
    reach2 = reach * reach
    for brick, cand in brick_candidates(tri, nb, reach).items():
        pts = owned_points(brick, nb).astype(np.float64)  # (P, 3)
        gap = np.maximum(
            np.maximum(tri.lo[cand][None] - pts[:, None], pts[:, None] - tri.hi[cand][None]), 0.0
        )
        box2 = (gap * gap).sum(axis=2)  # (P, K) squared distance to each triangle's box, a lower bound
        pi, ki = np.nonzero(box2 <= reach2)  # pairs that can be within reach
        d2 = np.full((len(pts), len(cand)), np.inf)  # (P, K)
        d2[pi, ki] = squared_distances(pts[pi], tri, cand[ki])
        best = np.argmin(d2, axis=1)  # (P,) first minimum = lowest triangle index
        best_d2 = d2[np.arange(len(pts)), best]  # (P,)
        ok = best_d2 <= reach2
        p = pts[ok].astype(np.int64)
        dist[p[:, 0], p[:, 1], p[:, 2]] = np.sqrt(best_d2[ok]).astype(np.float32)
        near[p[:, 0], p[:, 1], p[:, 2]] = cand[best[ok]]
    return Nearest(dist, near)


def brick_classes(tri: Triangles, face_class: np.ndarray, resolution: int, stored: np.ndarray) -> np.ndarray:
    """Class of the nearest drawn triangle within CLASS_REACH of each stored brick's centre lattice
    point (ties to the lowest index; 0 when none): (nb, nb, nb) uint8, 0 where not `stored`."""
    nb = resolution // BRICK_CELLS
    out = np.zeros((nb, nb, nb), np.uint8)  # (nb, nb, nb) uint8
    coords = np.argwhere(stored)  # (K, 3)
    if not len(coords) or not len(tri.a):
        return out
    centres = (coords * BRICK_CELLS + BRICK_CELLS // 2).astype(np.float64)  # (K, 3)
    all_idx = np.arange(len(tri.a))  # (T,)
    for k, centre in enumerate(centres):
        d2 = squared_distances(centre[None, :], tri, all_idx)  # (T,)
        best = int(np.argmin(d2))
        if d2[best] <= CLASS_REACH * CLASS_REACH:
            out[tuple(coords[k])] = face_class[best]
    return out
