"""Signed-distance and brick stages in PyTorch (`engine="torch"`): the reference stages on CPU or CUDA.

Every stage is one function mirroring its NumPy reference (distance.py, sign.py, farfield.py, sdf.py,
dag.py) and produces the same values bit for bit, so the file equals the reference engine's:
- distances: float64, the reference's formulas in the same operation order, one PyTorch operation per
  NumPy operation (no fused multiply-add: eager kernels never fuse two operations; every division by a
  constant divides by a full tensor, never a multiply by a reciprocal). Work is split into (triangle,
  4^3-point tile) pairs instead of bricks: a tile is kept when the triangle's plane comes within reach
  of it, and a point when its squared distance to the triangle's box is <= reach^2, as in the
  reference; the nearest triangle is the smallest squared distance, ties to the lowest index (two
  scatter-min passes), so the result does not depend on the split.
- fill: connected components of the non-wall lattice are unique, so any exact scheme gives the
  reference's result. Here: sweeps along x, y and z, each of which makes every run of non-wall points
  on a lattice line reached when one of its points is (cumulative max/min of run ids), repeated until
  the reached count stops changing (one host sync per x/y/z round).
- far field: only far bricks read the far field (a stored brick quantises every sample beyond reach
  to +-127 whatever its value), through the minimum of its 9^3 samples. The minimum of the squared
  EDT over a brick's lattice points is the squared distance from the brick's box to the nearest site,
  computed exactly in integers by three separable passes at brick resolution.
- DAG: brick classification, far codes and quantisation on the device; deduplication and node
  numbering on the host with the reference helpers (dag.py).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from navi_compiler.dag.build import HALF_DIAGONAL, DagArrays, _children, _merge_far, _renumber, dedup_rows
from navi_compiler.gmdag import (
    BRICK_CELLS,
    BRICK_SAMPLES,
    BRICK_SIDE,
    FAR_UNITS,
    FLAG_INSIDE_SEEDS,
    FLAG_LEAK_FALLBACK,
    TAG_BRICK,
    TAG_FAR_FREE,
    TAG_FAR_SOLID,
    TAG_NODE,
    quant_step_for,
)
from navi_compiler.sdf.distance import CLASS_REACH
from navi_compiler.sdf.farfield import NO_SITE, SURFACE_CELL
from navi_compiler.sdf.reference import REACH_MARGIN, SdfInput, drop_degenerate
from navi_compiler.sdf.sign import PROBE, WALL

F64 = torch.float64
MIN_SINE = 1e-6  # slivers thinner than this keep every tile of their box (no plane pruning)
PLANE_MARGIN = 1e-3  # voxels added to the tile's plane-distance test, far above its rounding error


@dataclass(frozen=True)
class TorchConfig:
    """Knobs of the torch engine (none changes the output)."""

    device: str = "cpu"  # torch device the stages run on ("cpu", "cuda", "cuda:1", ...)
    tile: int = 4  # lattice points per tile edge in the (triangle, tile) pair split
    chunk_pairs: int = 1 << 23  # (point, triangle) pairs evaluated per batch (bounds memory)
    chunk_tiles: int = 1 << 22  # (triangle, tile) pairs generated per batch


@dataclass(frozen=True)
class Tri:
    """Triangles in voxel coordinates on the device, with edges, boxes and plane normals."""

    a: torch.Tensor  # (T, 3) float64
    b: torch.Tensor  # (T, 3) float64
    c: torch.Tensor  # (T, 3) float64
    ab: torch.Tensor  # (T, 3) float64 b - a
    ac: torch.Tensor  # (T, 3) float64 c - a
    bc: torch.Tensor  # (T, 3) float64 c - b
    lo: torch.Tensor  # (T, 3) float64 box min
    hi: torch.Tensor  # (T, 3) float64 box max
    unit_normal: torch.Tensor  # (T, 3) float64 (only prunes tiles, conservatively)
    flat: torch.Tensor  # (T,) bool: the normal is well conditioned enough to prune with


@dataclass(frozen=True)
class Nearest:
    """Nearest triangle on a lattice of query points, where within reach."""

    distance: torch.Tensor  # (m, m, m) float32 of the float64 distance, +inf beyond reach
    triangle: torch.Tensor  # (m, m, m) int32 nearest triangle index, -1 beyond reach


@dataclass(frozen=True)
class FillT:
    """Outcome of the flood fill (as sign.Fill)."""

    reached: torch.Tensor  # (R+1, R+1, R+1) bool free non-wall points
    inside_seeded: bool  # started from seeds and did not leak
    leaked: bool  # seeded from inside, reached the border, fell back to the border
    seeds_used: int  # seeds that found a non-wall start point


@dataclass(frozen=True)
class TorchResult:
    """What the torch engine hands to the file stage."""

    arrays: DagArrays  # the octree
    flags: int  # GMDAG flag bits
    seeds_used: int  # seeds that started the fill
    wall_points: int  # lattice points within 1/2 voxel of a drawn or barrier triangle
    free_points: int  # lattice points with a positive sign
    stage_seconds: dict[str, float] = field(default_factory=dict)  # wall time per stage


def make_tri(corners: np.ndarray, device: torch.device) -> Tri:
    """(T, 3, 3) float64 corners (voxels, non-degenerate) -> Tri on `device`."""
    t = torch.as_tensor(corners, dtype=F64, device=device)  # (T, 3, 3) float64
    a, b, c = t[:, 0].contiguous(), t[:, 1].contiguous(), t[:, 2].contiguous()  # (T, 3) each
    ab, ac = b - a, c - a  # (T, 3)
    n = torch.linalg.cross(ab, ac)  # (T, 3)
    norm = n.norm(dim=1)  # (T,) twice the area
    unit = n / norm[:, None]  # (T, 3)
    # sin(angle at a) >= 1e-6: the normal's direction error (~1e-16 / sin) stays far below the margin
    flat = norm >= MIN_SINE * ab.norm(dim=1) * ac.norm(dim=1)  # (T,)
    return Tri(
        a,
        b,
        c,
        ab,
        ac,
        c - b,
        torch.minimum(torch.minimum(a, b), c),
        torch.maximum(torch.maximum(a, b), c),
        unit,
        flat,
    )


def _dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def _div(num: float, den: torch.Tensor) -> torch.Tensor:
    """num / den elementwise as a true division (never a multiply by a reciprocal)."""
    return torch.full_like(den, num) / den


def closest_points(p: torch.Tensor, tri: Tri, idx: torch.Tensor) -> torch.Tensor:
    """distance.closest_points in torch: p (P, 3) float64, idx (P,) int64 -> (P, 3) float64."""
    a, b, c = tri.a[idx], tri.b[idx], tri.c[idx]  # (P, 3)
    ab, ac, bc = tri.ab[idx], tri.ac[idx], tri.bc[idx]  # (P, 3)
    ap, bp, cp = p - a, p - b, p - c  # (P, 3)
    d1, d2 = _dot(ab, ap), _dot(ac, ap)  # (P,)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)  # (P,)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)  # (P,)
    vc = d1 * d4 - d3 * d2  # (P,)
    vb = d5 * d2 - d1 * d6  # (P,)
    va = d3 * d6 - d5 * d4  # (P,)
    in_a = (d1 <= 0) & (d2 <= 0)
    in_b = (d3 >= 0) & (d4 <= d3)
    in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    in_c = (d6 >= 0) & (d5 <= d6)
    in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    in_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    v_ab = d1 / (d1 - d3)  # (P,)
    w_ac = d2 / (d2 - d6)  # (P,)
    w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))  # (P,)
    denom = _div(1.0, va + vb + vc)  # (P,)
    v_in, w_in = vb * denom, vc * denom  # (P,)
    out = a + ab * v_in[:, None] + ac * w_in[:, None]  # (P, 3)
    conds = [in_a, in_b, in_ab, in_c, in_ac, in_bc]
    choices = [a, b, a + v_ab[:, None] * ab, c, a + w_ac[:, None] * ac, b + w_bc[:, None] * bc]
    for cond, q in zip(reversed(conds), reversed(choices), strict=True):
        out = torch.where(cond[:, None], q, out)  # (P, 3) float64
    return out


def squared_distances(p: torch.Tensor, tri: Tri, idx: torch.Tensor) -> torch.Tensor:
    """|p - closest point|^2 as dx*dx + dy*dy + dz*dz: (P,) float64."""
    d = p - closest_points(p, tri, idx)  # (P, 3)
    return d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]


def _tile_pairs(
    tri: Tri, stride: int, offset: int, m: int, reach: float, cfg: TorchConfig
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Batches of (triangle (K,) int64, first point index (K, 3) int64, last point index (K, 3) int64):
    tiles of cfg.tile^3 query points (index i at offset + stride * i, i in [0, m)) inside the
    triangle's box grown by reach, whose centre lies within reach + the tile's half diagonal of the
    triangle's plane (plus PLANE_MARGIN; slivers keep every tile)."""
    dev = tri.a.device
    s = cfg.tile
    first = torch.ceil((tri.lo - reach - offset) / stride).clamp(0, m - 1).long()  # (T, 3)
    last = torch.floor((tri.hi + reach - offset) / stride).clamp(0, m - 1).long()  # (T, 3)
    inside = ((tri.hi + reach - offset) >= 0).all(1) & ((tri.lo - reach - offset) <= stride * (m - 1)).all(1)
    ext = torch.where(inside[:, None] & (last >= first), last - first + 1, 0)  # (T, 3) points per axis
    tiles = (ext + s - 1) // s  # (T, 3)
    count = tiles.prod(1)  # (T,)
    ends = torch.cumsum(count, 0).cpu()  # (T,) host sync: batch boundaries
    batches: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    radius = stride * (s - 1) * 0.5 * math.sqrt(3.0) + reach + PLANE_MARGIN  # voxels
    start_t, done = 0, 0
    while start_t < len(count):
        stop_t = int(torch.searchsorted(ends, done + cfg.chunk_tiles, right=True))
        stop_t = max(stop_t, start_t + 1)
        n_tiles = int(ends[stop_t - 1]) - done
        tids = torch.arange(start_t, stop_t, device=dev)  # (t,)
        t = torch.repeat_interleave(tids, count[start_t:stop_t], output_size=n_tiles)  # (K,)
        base = torch.cumsum(count[start_t:stop_t], 0) - count[start_t:stop_t]  # (t,)
        local = torch.arange(n_tiles, device=dev) - base[t - start_t]  # (K,)
        ty, tz = tiles[t, 1], tiles[t, 2]  # (K,)
        k = torch.stack([local // (ty * tz), (local // tz) % ty, local % tz], 1)  # (K, 3) tile coords
        lo_i = first[t] + k * s  # (K, 3) first point index of the tile
        hi_i = torch.minimum(lo_i + (s - 1), first[t] + ext[t] - 1)  # (K, 3)
        centre = (lo_i + hi_i).double() * (0.5 * stride) + offset  # (K, 3) float64 voxels
        plane = _dot(centre - tri.a[t], tri.unit_normal[t]).abs()  # (K,)
        keep = (plane <= radius) | ~tri.flat[t]  # (K,)
        batches.append((t[keep], lo_i[keep], hi_i[keep]))
        done = int(ends[stop_t - 1])
        start_t = stop_t
    return batches


def nearest_within(tri: Tri, stride: int, offset: int, m: int, reach: float, cfg: TorchConfig) -> Nearest:
    """Nearest triangle within `reach` of every query point offset + stride * (i, j, k), i, j, k in
    [0, m): the smallest squared distance, ties to the lowest index (as distance.nearest_triangles)."""
    dev = tri.a.device
    s = cfg.tile
    best = torch.full((m * m * m,), math.inf, dtype=F64, device=dev)  # (m^3,) float64
    if len(tri.a) == 0:
        empty = torch.full((m, m, m), -1, dtype=torch.int32, device=dev)  # (m, m, m) int32
        return Nearest(best.view(m, m, m).to(torch.float32), empty)
    reach2 = reach * reach
    grid = torch.stack(torch.meshgrid(*[torch.arange(s, device=dev)] * 3, indexing="ij"), -1).reshape(
        -1, 3
    )  # (s^3, 3) int64 offsets inside a tile
    kept: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []  # (flat, triangle, d2) per batch
    step = max(1, cfg.chunk_pairs // (s**3))
    for t_all, lo_all, hi_all in _tile_pairs(tri, stride, offset, m, reach, cfg):
        for j in range(0, len(t_all), step):
            t, lo_i, hi_i = t_all[j : j + step], lo_all[j : j + step], hi_all[j : j + step]  # (K,), (K, 3)
            idx = lo_i[:, None, :] + grid[None]  # (K, s^3, 3) int64 point indices
            valid = (idx <= hi_i[:, None, :]).all(2)  # (K, s^3)
            pi, gi = torch.nonzero(valid, as_tuple=True)  # (P,), (P,)
            pt_idx = idx[pi, gi]  # (P, 3)
            tt = t[pi]  # (P,)
            p = pt_idx.double() * stride + offset  # (P, 3) float64 voxels
            gap = torch.maximum(torch.maximum(tri.lo[tt] - p, p - tri.hi[tt]), torch.zeros_like(p))  # (P, 3)
            box2 = (gap * gap).sum(1)  # (P,)
            ok = box2 <= reach2  # (P,)
            p, tt, pt_idx = p[ok], tt[ok], pt_idx[ok]
            d2 = squared_distances(p, tri, tt)  # (P',) float64
            ok = d2 <= reach2
            flat = (pt_idx[ok, 0] * m + pt_idx[ok, 1]) * m + pt_idx[ok, 2]  # (Q,) int64
            best.scatter_reduce_(0, flat, d2[ok], reduce="amin")
            kept.append((flat, tt[ok], d2[ok]))
    big = torch.iinfo(torch.int32).max
    tie = torch.full((m * m * m,), big, dtype=torch.int32, device=dev)  # (m^3,) int32
    for flat, tt, d2 in kept:
        win = d2 == best[flat]  # (Q,)
        tie.scatter_reduce_(0, flat[win], tt[win].to(torch.int32), reduce="amin")
    del kept
    near = torch.where(tie == big, -1, tie).view(m, m, m)  # (m, m, m) int32
    return Nearest(best.sqrt_().to(torch.float32).view(m, m, m), near)


def band_distances(tri: Tri, resolution: int, reach: float, cfg: TorchConfig) -> Nearest:
    """Distance stage: exact nearest triangle within reach on the (R+1)^3 lattice."""
    return nearest_within(tri, 1, 0, resolution + 1, reach, cfg)


def walls(drawn: torch.Tensor, barrier: torch.Tensor) -> torch.Tensor:
    """Wall points: float32 distance to a drawn or barrier triangle <= WALL: (R+1)^3 bool."""
    return (drawn <= WALL) | (barrier <= WALL)


def seed_starts(seeds: np.ndarray, wall: torch.Tensor) -> np.ndarray:
    """sign.seed_starts on the device wall grid (reads only the 8 corners of each seed's cell)."""
    r = wall.shape[0] - 1
    corners = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)  # (8, 3)
    inside = [s for s in seeds if ((s >= 0.0) & (s <= float(r))).all()]
    if not inside:
        return np.zeros((0, 3), np.int64)
    pts = np.stack([np.minimum(np.floor(s).astype(np.int64), r - 1) + corners for s in inside])  # (S, 8, 3)
    look = torch.as_tensor(pts.reshape(-1, 3), device=wall.device)  # (S*8, 3)
    blocked = wall[look[:, 0], look[:, 1], look[:, 2]].cpu().numpy().reshape(len(inside), 8)  # (S, 8) bool
    starts: list[np.ndarray] = []
    for s, p, b in zip(inside, pts, blocked, strict=True):
        diff = p - s  # (8, 3) float64
        d2 = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2]  # (8,)
        for c in np.lexsort((np.arange(8), d2)):
            if not b[c]:
                starts.append(p[c])
                break
    return np.array(starts, np.int64).reshape(-1, 3)


def _sweep(reached: torch.Tensor, wall: torch.Tensor, run: torch.Tensor, axis: int) -> torch.Tensor:
    """Reach every non-wall run along `axis` that holds a reached point. run: run id per point along
    the axis (cumulative wall count), int16."""
    info = torch.iinfo(torch.int16)
    mark = torch.where(reached, run, info.min)  # (n, n, n) int16
    left = torch.cummax(mark, axis).values == run  # a reached point at or before, same run
    back = torch.flip(torch.where(reached, run, info.max), (axis,))  # (n, n, n) int16
    right = torch.flip(torch.cummin(back, axis).values, (axis,)) == run  # at or after, same run
    return (left | right) & ~wall


def flood(start: torch.Tensor, wall: torch.Tensor, stop_on_border: bool) -> tuple[torch.Tensor, bool]:
    """6-connected fill of non-wall points from `start` (as sign.flood), by run sweeps along x, y, z
    until the reached count stops changing. Returns (reached, touched the border). With
    stop_on_border, stops as soon as the border is reached (the caller falls back)."""
    runs = [torch.cumsum(wall, axis, dtype=torch.int16) for axis in range(3)]  # 3 x (n, n, n) int16
    reached = start & ~wall  # (n, n, n) bool
    count = -1
    while True:
        for axis in range(3):
            reached = _sweep(reached, wall, runs[axis], axis)
        faces = (reached[0], reached[-1], reached[:, 0], reached[:, -1], reached[:, :, 0], reached[:, :, -1])
        on_border = torch.stack([f.any() for f in faces]).any()  # () bool
        border_now, total = torch.stack([on_border.long(), reached.sum()]).tolist()  # one host sync
        border, now = bool(border_now), int(total)
        if now == count or (border and stop_on_border):
            return reached, border
        count = now


def fill(seeds: np.ndarray, wall: torch.Tensor) -> FillT:
    """sign.fill: from the seeds (voxels), with leak detection and the border fallback."""
    n = wall.shape[0]
    edge = torch.zeros_like(wall)  # (n, n, n) bool
    edge[[0, -1]] = True
    edge[:, [0, -1]] = True
    edge[:, :, [0, -1]] = True
    starts = seed_starts(seeds, wall)  # (K, 3)
    if len(starts):
        start = torch.zeros((n, n, n), dtype=torch.bool, device=wall.device)  # (n, n, n) bool
        s = torch.as_tensor(starts, device=wall.device)  # (K, 3)
        start[s[:, 0], s[:, 1], s[:, 2]] = True
        reached, leaked = flood(start, wall, True)
        if not leaked:
            return FillT(reached, True, False, len(starts))
        return FillT(flood(edge, wall, False)[0], False, True, len(starts))
    return FillT(flood(edge, wall, False)[0], False, False, 0)


def _probe_reached(points: torch.Tensor, reached: torch.Tensor) -> torch.Tensor:
    r = reached.shape[0] - 1
    idx = torch.floor(points + 0.5).clamp(0, r).long()  # (P, 3)
    return reached[idx[:, 0], idx[:, 1], idx[:, 2]]


def _probes(
    pts: torch.Tensor, tri: Tri, near: torch.Tensor, reached: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    q = closest_points(pts, tri, near)  # (P, 3)
    d = pts - q  # (P, 3)
    u = torch.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])  # (P,)
    off = u > 0.0  # (P,)
    step = torch.where(off[:, None], d * _div(PROBE, u)[:, None], torch.zeros_like(d))  # (P, 3)
    return _probe_reached(q + step, reached), _probe_reached(q - step, reached), off


def signs(
    drawn: torch.Tensor,
    drawn_near: torch.Tensor,
    barrier: torch.Tensor,
    barrier_near: torch.Tensor,
    tri: Tri,
    bar: Tri,
    filled: FillT,
) -> torch.Tensor:
    """sign.signs: +1 / -1 per lattice point ((R+1)^3 int8)."""
    drawn_wall = drawn <= WALL  # (n, n, n) bool
    barrier_wall = (barrier <= WALL) & ~drawn_wall  # (n, n, n) bool
    out = torch.where(filled.reached, 1, -1).to(torch.int8)  # (n, n, n) int8
    for mask, t, nearest in ((drawn_wall, tri, drawn_near), (barrier_wall, bar, barrier_near)):
        pts = torch.nonzero(mask)  # (P, 3) int64
        if len(pts) == 0:
            continue
        mine, other, off = _probes(pts.double(), t, nearest[mask].long(), filled.reached)
        out[mask] = torch.where(mine & ~other & off, 1, -1).to(torch.int8)
    return out


def surface_corners(distance: torch.Tensor) -> torch.Tensor:
    """farfield.surface_corners: corners of every cell with a corner within sqrt(3)/2: (n, n, n) bool."""
    close = distance <= float(SURFACE_CELL)  # (n, n, n) bool
    r = close.shape[0] - 1
    cell = torch.zeros((r, r, r), dtype=torch.bool, device=close.device)  # (R, R, R) bool
    for c in range(8):
        x, y, z = c & 1, (c >> 1) & 1, (c >> 2) & 1
        cell |= close[x : x + r, y : y + r, z : z + r]
    corners = torch.zeros_like(close)  # (n, n, n) bool
    for c in range(8):
        x, y, z = c & 1, (c >> 1) & 1, (c >> 2) & 1
        corners[x : x + r, y : y + r, z : z + r] |= cell
    return corners


def _gap2(nb: int, n: int, device: torch.device) -> torch.Tensor:
    """Squared distance from lattice coordinate i to the brick interval [8b, 8b+8]: (nb, n) int64."""
    b = torch.arange(nb, device=device)[:, None] * BRICK_CELLS  # (nb, 1)
    i = torch.arange(n, device=device)[None, :]  # (1, n)
    gap = torch.clamp(torch.maximum(b - i, i - b - BRICK_CELLS), min=0)  # (nb, n)
    return gap * gap


def brick_min_edt(sites: torch.Tensor) -> torch.Tensor:
    """min over each brick's 9^3 lattice points of the exact squared EDT to `sites` ((n, n, n) bool):
    (nb, nb, nb) int64, >= NO_SITE where there is no site. Separable: x to bricks through the nearest
    site on each side, then exact min-plus over y and z at brick resolution."""
    n = sites.shape[0]
    nb = (n - 1) // BRICK_CELLS
    dev = sites.device
    i = torch.arange(n, device=dev).view(n, 1, 1)  # (n, 1, 1)
    last = torch.cummax(torch.where(sites, i, -1), 0).values  # (n, n, n) last site index <= x
    first = torch.flip(
        -torch.cummax(torch.flip(torch.where(sites, -i, -(1 << 40)), (0,)), 0).values, (0,)
    )  # (n, n, n) first site index >= x (2^40: none)
    lo = torch.arange(nb, device=dev) * BRICK_CELLS  # (nb,)
    left = last[lo + BRICK_CELLS]  # (nb, n, n) last site <= 8b+8
    right = first[lo]  # (nb, n, n) first site >= 8b
    lo3 = lo.view(nb, 1, 1)
    d_left = torch.where(left >= 0, torch.clamp(lo3 - left, min=0), NO_SITE)  # (nb, n, n)
    d_right = torch.where(right < (1 << 40), torch.clamp(right - lo3 - BRICK_CELLS, min=0), NO_SITE)
    g = torch.minimum(torch.minimum(d_left * d_left, d_right * d_right), torch.full_like(d_left, NO_SITE))
    gap2 = _gap2(nb, n, dev)  # (nb, n) int64
    gy = torch.stack([(g + gap2[b].view(1, n, 1)).amin(1) for b in range(nb)], 1)  # (nb, nb, n) [bx, by, z]
    gz = torch.stack([(gy + gap2[b].view(1, 1, n)).amin(2) for b in range(nb)], 2)  # (nb, nb, nb)
    return torch.clamp(gz, max=NO_SITE)


def lower_bound(d2: torch.Tensor) -> torch.Tensor:
    """farfield.lower_bound: squared distances -> sqrt rounded down to float32 (+inf at NO_SITE)."""
    exact = torch.sqrt(d2.double())  # float64
    low = exact.to(torch.float32)  # float32 round to nearest
    low = torch.where(low.double() > exact, torch.nextafter(low, torch.zeros_like(low)), low)  # float32
    return torch.where(d2 >= NO_SITE, torch.full_like(low, math.inf), low)


def brick_reduce(
    lattice: torch.Tensor, op: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
) -> torch.Tensor:
    """dag.brick_reduce: op over every brick's 9^3 window (stride 8): (nb, nb, nb)."""
    out = lattice
    for axis in range(3):
        nb = (out.shape[axis] - 1) // BRICK_CELLS
        sl = [slice(None)] * 3
        sl[axis] = slice(0, BRICK_CELLS * nb, BRICK_CELLS)
        acc = out[tuple(sl)]
        for offset in range(1, BRICK_SIDE):
            sl[axis] = slice(offset, offset + BRICK_CELLS * nb, BRICK_CELLS)
            acc = op(acc, out[tuple(sl)])
        out = acc
    return out


def quantise(samples: torch.Tensor, quant_step: float) -> torch.Tensor:
    """dag.quantise: float32 samples -> int8 codes, never decoding farther from zero."""
    step = torch.full_like(samples, quant_step)  # float32, a full tensor: a true division
    q = torch.clamp(torch.trunc(samples / step), -127, 127)  # float32
    over = (q * step).abs() > samples.abs()
    q = q - torch.sign(q) * over.to(q.dtype)  # float32
    return q.to(torch.int8)


def bricks(
    distance: torch.Tensor,
    sign: torch.Tensor,
    edt_min: torch.Tensor,
    reach: float,
    band: float,
    resolution: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Assembly + brick classification + far codes + quantisation (sdf.assemble, dag.build_dag):
    returns (stored (nb, nb, nb) bool, words (nb, nb, nb) int64 far words, coords (K, 3) int64,
    codes (K, 729) int8). Far-field values beyond reach are written as reach in the lattice (a stored
    brick quantises both to +-127); far bricks take min(min exact |sample|, far bound) from edt_min."""
    band32 = float(np.float32(band))
    reach32 = float(np.float32(reach))
    finite = torch.isfinite(distance)  # (n, n, n) bool
    lattice = torch.where(finite, distance, torch.full_like(distance, reach32)) * sign.to(torch.float32)
    bmin = brick_reduce(lattice, torch.minimum)  # (nb, nb, nb) float32
    bmax = brick_reduce(lattice, torch.maximum)  # (nb, nb, nb) float32
    fmin = brick_reduce(torch.where(finite, distance, torch.full_like(distance, math.inf)), torch.minimum)
    far_value = torch.clamp(
        torch.minimum(lower_bound(edt_min), torch.full_like(fmin, 2 * resolution)), min=reach32
    )
    lower = torch.minimum(fmin, far_value) - float(HALF_DIAGONAL)  # (nb, nb, nb) float32
    far_free = bmin >= band32
    far_solid = bmax <= -band32
    scaled = torch.floor(torch.clamp(lower, min=0.0) * float(FAR_UNITS))  # float32
    payload = torch.clamp(scaled, max=float(1 << 29)).long()  # (nb, nb, nb) int64
    words = torch.where(far_free, (TAG_FAR_FREE << 30) | payload, (TAG_FAR_SOLID << 30) | payload)
    stored = ~(far_free | far_solid)  # (nb, nb, nb) bool
    coords = torch.nonzero(stored)  # (K, 3) x-major scan order
    windows = (
        lattice.unfold(0, BRICK_SIDE, BRICK_CELLS)
        .unfold(1, BRICK_SIDE, BRICK_CELLS)
        .unfold(2, BRICK_SIDE, BRICK_CELLS)
    )  # (nb, nb, nb, 9, 9, 9) view [bx, by, bz, x, y, z]
    picked = windows[coords[:, 0], coords[:, 1], coords[:, 2]]  # (K, 9, 9, 9)
    samples = picked.permute(0, 3, 2, 1).reshape(len(coords), BRICK_SAMPLES)  # (K, 729) file order
    return stored, words, coords, quantise(samples, quant_step_for(band32))


def brick_classes(tri: Tri, face_class: torch.Tensor, stored: torch.Tensor, cfg: TorchConfig) -> torch.Tensor:
    """distance.brick_classes: class of the nearest drawn triangle within CLASS_REACH of each stored
    brick's centre lattice point (ties to the lowest index, 0 when none): (nb, nb, nb) uint8."""
    nb = stored.shape[0]
    if len(face_class) == 0:
        return torch.zeros_like(stored, dtype=torch.uint8)
    near = nearest_within(tri, BRICK_CELLS, BRICK_CELLS // 2, nb, CLASS_REACH, cfg).triangle  # (nb,)*3
    cls = torch.where(near >= 0, face_class[near.clamp(min=0).long()], torch.zeros_like(face_class[:1]))
    return torch.where(stored, cls, torch.zeros_like(cls)).to(torch.uint8)


def assemble_dag(words: np.ndarray, stored: np.ndarray, codes: np.ndarray, classes: np.ndarray) -> DagArrays:
    """The host half of dag.build_dag: dedup bricks, build, merge and dedup nodes, number them."""
    nb = words.shape[0]
    levels = int(math.log2(nb))
    keys = np.concatenate([codes.view(np.uint8), classes[:, None]], axis=1)  # (K, 730) uint8
    brick_ids, brick_first = dedup_rows(keys)  # (K,), (U,)
    words = words.copy()
    words[stored] = (TAG_BRICK << 30) | brick_ids.astype(np.uint32)
    level_nodes: list[np.ndarray] = [np.zeros((0, 8), np.uint32)] * levels  # per depth (P_d, 8) uint32
    for d in range(levels - 1, -1, -1):
        n = 1 << d
        children = _children(words).reshape(n**3, 8)  # (n^3, 8) uint32
        merged = _merge_far(children)  # (n^3,) uint32
        stays = merged == 0
        node_ids, node_first = dedup_rows(np.ascontiguousarray(children[stays]).view(np.uint8))
        level_nodes[d] = children[stays][node_first]  # (P, 8) uint32
        merged[stays] = (TAG_NODE << 30) | node_ids.astype(np.uint32)
        words = merged.reshape(n, n, n)
    root, nodes, brick_order = _renumber(int(words.reshape(-1)[0]), levels, level_nodes)
    return DagArrays(
        root=root,
        levels=levels,
        nodes=nodes,
        bricks=np.ascontiguousarray(codes[brick_first[brick_order]]),
        brick_class=np.ascontiguousarray(keys[brick_first[brick_order], BRICK_SAMPLES]),
    )


def compile_torch(inp: SdfInput, cfg: TorchConfig) -> TorchResult:
    """All stages from voxel-space triangles to the octree, on cfg.device."""
    dev = torch.device(cfg.device)
    seconds: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(stage: str) -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        now = time.perf_counter()
        seconds[stage] = now - clock[0]
        clock[0] = now

    drawn_np, classes_np = drop_degenerate(inp.drawn, inp.face_class)
    barrier_np, _ = drop_degenerate(inp.barrier, np.zeros(len(inp.barrier), np.uint8))
    tri, bar = make_tri(drawn_np, dev), make_tri(barrier_np, dev)
    face_class = torch.as_tensor(classes_np, device=dev).long()  # (F,) int64
    lap("upload")
    reach = float(np.float32(inp.band)) + REACH_MARGIN
    near_drawn = band_distances(tri, inp.resolution, reach, cfg)
    drawn = near_drawn.distance  # (n, n, n) float32
    lap("distance")
    near_barrier = band_distances(bar, inp.resolution, reach, cfg)
    barrier = near_barrier.distance  # (n, n, n) float32
    lap("barrier")
    wall = walls(drawn, barrier)  # (n, n, n) bool
    filled = fill(inp.seeds, wall)
    lap("fill")
    sign = signs(drawn, near_drawn.triangle, barrier, near_barrier.triangle, tri, bar, filled)
    surface = torch.minimum(drawn, barrier)  # (n, n, n) float32: drawn and barrier surfaces (sdf.py)
    del near_barrier, barrier
    lap("sign")
    sites = surface_corners(surface)  # (n, n, n) bool
    lap("surface cells")
    edt_min = brick_min_edt(sites)  # (nb, nb, nb) int64
    lap("edt")
    stored, words, coords, codes = bricks(surface, sign, edt_min, reach, inp.band, inp.resolution)
    lap("assemble")
    cls = brick_classes(tri, face_class, stored, cfg)  # (nb, nb, nb) uint8
    picked = cls[coords[:, 0], coords[:, 1], coords[:, 2]]  # (K,) uint8
    wall_points, free_points = int(wall.sum()), int((sign > 0).sum())
    words_np = words.cpu().numpy().astype(np.uint32)  # (nb, nb, nb) uint32
    stored_np, codes_np, picked_np = stored.cpu().numpy(), codes.cpu().numpy(), picked.cpu().numpy()
    lap("classes")
    arrays = assemble_dag(words_np, stored_np, codes_np, picked_np)
    lap("dag")
    flags = (FLAG_INSIDE_SEEDS if filled.inside_seeded else 0) | (FLAG_LEAK_FALLBACK if filled.leaked else 0)
    return TorchResult(arrays, flags, filled.seeds_used, wall_points, free_points, seconds)
