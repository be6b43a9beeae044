"""Far-field stage (NumPy reference; csrc/farfield.h is the C++ twin): a lower bound of the distance
everywhere, from an exact Euclidean distance transform.

A cell can hold a surface point only if one of its corners is within sqrt(3)/2 voxel of the surface
(every point of a cell is that close to a corner), so the *surface cells* are the cells with a corner
whose exact distance is <= sqrt(3)/2. For a lattice point p the nearest point of any cell is one of
its corners (clamping integer coordinates to a cell gives a corner), so the exact EDT of p to the
corners of all surface cells, D(p), is the distance from p to the union of surface cells, and the
true distance is >= D(p). D^2 is an integer, computed exactly (separable lower envelope of parabolas);
the bound is sqrt(D^2) rounded down to float32. With no surface cell at all, D is +inf.
"""

from __future__ import annotations

import math

import numpy as np

SURFACE_CELL = np.float32(math.sqrt(3.0) / 2.0)  # voxels, compared with the float32 distances
NO_SITE = 1 << 30  # squared distance meaning "no site" (any real one is < 3 * 4097^2 < 2^26)


def surface_corners(distance: np.ndarray) -> np.ndarray:
    """(R+1)^3 float32 exact distances (+inf far) -> (R+1)^3 bool: corners of every surface cell."""
    close = distance <= SURFACE_CELL  # (n, n, n)
    cell = np.zeros(tuple(s - 1 for s in close.shape), bool)  # (R, R, R): any corner close
    for c in range(8):
        x, y, z = c & 1, (c >> 1) & 1, (c >> 2) & 1
        cell |= close[x : x + cell.shape[0], y : y + cell.shape[1], z : z + cell.shape[2]]
    corners = np.zeros_like(close)  # (n, n, n) bool
    for c in range(8):
        x, y, z = c & 1, (c >> 1) & 1, (c >> 2) & 1
        corners[x : x + cell.shape[0], y : y + cell.shape[1], z : z + cell.shape[2]] |= cell
    return corners


def _min_plus_axis(f: np.ndarray, axis: int) -> np.ndarray:
    """g[i] = min_j f[j] + (i - j)^2 along `axis` (exact int64), in chunks to bound memory."""
    f = np.moveaxis(f, axis, -1)
    n = f.shape[-1]
    j = np.arange(n, dtype=np.int64)  # (n,)
    cost = (j[:, None] - j[None, :]) ** 2  # (n, n) [i, j]
    flat = f.reshape(-1, n)  # (L, n)
    out = np.empty_like(flat)  # (L, n) int64
    chunk = max(1, (1 << 24) // (n * n))
    for s in range(0, len(flat), chunk):
        out[s : s + chunk] = (flat[s : s + chunk, None, :] + cost[None]).min(axis=2)
    return np.moveaxis(out.reshape(f.shape), -1, axis)


def squared_edt(sites: np.ndarray) -> np.ndarray:
    """Exact squared Euclidean distance (int32, NO_SITE where there is no site) to the nearest
    True point of `sites` ((n, n, n) bool), by three separable min-plus passes."""
    f = np.where(sites, np.int64(0), np.int64(NO_SITE))  # (n, n, n) int64
    for axis in range(3):
        f = np.minimum(_min_plus_axis(f, axis), NO_SITE)
    return f.astype(np.int32)


def lower_bound(d2: np.ndarray) -> np.ndarray:
    """Squared distances (int32) -> sqrt rounded down to float32 (+inf where there is no site)."""
    exact = np.sqrt(d2.astype(np.float64))  # float64
    low = exact.astype(np.float32)  # float32, round to nearest
    low = np.where(low.astype(np.float64) > exact, np.nextafter(low, np.float32(0)), low)  # float32
    return np.where(d2 >= NO_SITE, np.float32(np.inf), low).astype(np.float32)
