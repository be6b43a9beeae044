"""Procedural scenes: the embedded default corpus (no download), built from boxes and cylinders.

Every scene is a `Layout`: the interior is the union of axis-aligned *air* boxes carved out of
solid rock (its boundary becomes floor / wall / ceiling faces), plus solid obstacles standing in
that air (pillars, trunks, crates, stairs, and oriented slabs: ramps, balconies, slanted struts,
railings). Open families (forest, yard, platforms) have no drawn roof: the top of the interior
becomes an undrawn barrier, like a Quake 3 sky; the floating family has no drawn boundary at all (a
space map's sky box above, below and around). World meters, +Z up, the
floor at z = 0. Passages are sized for a drone of radius 0.3 m (doorways ≥ 1.2 m wide, corridors
and tunnels ≥ 1.6 m wide, obstacles ≥ 1.4 m apart).

Shapes: V vertices, F faces, Fb barrier faces, S seeds, Q quads, Nx/Ny/Nz grid cells.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path

import numpy as np

from navi_compiler.ingest import bsp
from navi_compiler.ingest.sidecar import Sidecar, write_sidecar
from navi_compiler.scene import Scene


class Family(StrEnum):
    """The procedural scene families (see docs/SCENES.md)."""

    ROOMS = "rooms"
    CORRIDORS = "corridors"
    HALL = "hall"
    MAZE = "maze"
    CAVES = "caves"
    FOREST = "forest"
    BUILDING = "building"
    YARD = "yard"
    ARENA = "arena"
    PLATFORMS = "platforms"
    FLOATING = "floating"
    FIELD = "field"


FAMILIES: tuple[Family, ...] = tuple(Family)
DEFAULT_ENTRIES: tuple[str, ...] = (
    *(f.value for f in Family if f not in (Family.FLOATING, Family.FIELD)),
    "arena@4",
    "platforms@4",
    "floating@4",
)
"""The entries a corpus cycles when none are named (the main job's corpus): every family but floating at
its own size, then arenas, platforms and floating decks scaled by up to 4 (parse_entry), whose views are
clear for 10 m all round as on large real maps. Against the ten families alone this corpus flew the 50
OpenArena maps with fewer collisions and the same coverage (docs/TRAINING.md, "Real maps never seen");
the floating family at its own size did not help there, and it and the field family are built only when
named."""

CLASS_NAMES = (
    "unknown",
    "floor",
    "wall",
    "ceiling",
    "pillar",
    "trunk",
    "obstacle",
    "stairs",
    "ramp",
    "railing",
)
FLOOR, WALL, CEILING, PILLAR, TRUNK, OBSTACLE, STAIRS, RAMP, RAILING = 1, 2, 3, 4, 5, 6, 7, 8, 9


class Semantics(StrEnum):
    """What a scene's face classes name (the semantic channel the drone sees)."""

    OBJECT = "object"
    """What each face belongs to: floor, wall, ceiling of the air, and the solid's kind (CLASS_NAMES)."""
    SURFACE = "surface"
    """What a Quake 3 map's faces say (navi_compiler.ingest.bsp.CLASS_NAMES): floor, wall or ceiling by the
    face's normal, and patch for the curved sides of cylinders. Solids then read as real maps' brushes."""


SEMANTICS: tuple[Semantics, ...] = tuple(Semantics)

DRONE_RADIUS = 0.3  # meters
SEED_CLEARANCE = 0.5  # meters of free space around every seed (drone radius plus a margin)
SEED_COUNT = 12  # seeds per scene (fewer when the free space is small)
CYLINDER_SEGMENTS = 16
SCALE_STREAM = 1
"""Third word of the seed sequence (seed, scene index, SCALE_STREAM) that draws a scene's scale."""


@dataclass(frozen=True)
class Box:
    """Axis-aligned box, meters."""

    lo: tuple[float, float, float]  # min corner (x, y, z)
    hi: tuple[float, float, float]  # max corner (x, y, z)


@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder, meters."""

    x: float  # axis position
    y: float
    radius: float
    z0: float  # bottom
    z1: float  # top


@dataclass(frozen=True)
class Slab:
    """Oriented box, meters: a centre, half extents along three orthonormal axes (ramps, tilted struts,
    balconies, rails)."""

    centre: tuple[float, float, float]
    half: tuple[float, float, float]  # half extents along axes[0], axes[1], axes[2]
    axes: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]

    def corners(self) -> np.ndarray:
        """The 8 corners (8, 3), bit order (x, y, z) of the local signs as in _box_quads."""
        signs = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))  # (8, 3)
        local = signs * np.array(self.half)  # (8, 3)
        return np.array(self.centre) + local @ np.array(self.axes)  # (8, 3)


def slab_between(
    a: Sequence[float], b: Sequence[float], width: float, thickness: float, top: bool = True
) -> Slab:
    """A slab of `width` whose centre line runs from point a to point b (3,) meters, `thickness` thick
    across it; with `top` the segment lies on its upper face (a ramp's walking surface), else on its axis
    (a beam). a and b must not lie on one vertical line."""
    p, q = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    along = (q - p) / np.linalg.norm(q - p)  # (3,)
    side = np.cross([0.0, 0.0, 1.0], along)  # (3,) horizontal, across the slab
    side /= np.linalg.norm(side)
    normal = np.cross(along, side)  # (3,) the slab's up
    centre = (p + q) / 2 - (normal * thickness / 2 if top else 0.0)
    half = (float(np.linalg.norm(q - p)) / 2, width / 2, thickness / 2)
    rows = tuple(tuple(round(float(v), 9) for v in axis) for axis in (along, side, normal))
    return Slab(tuple(round(float(v), 4) for v in centre), half, rows)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Solid:
    """An obstacle standing in the air: its shape and its face class id."""

    shape: Box | Cylinder | Slab
    cls: int  # index into CLASS_NAMES


@dataclass(frozen=True)
class Layout:
    """The primitives of one scene, before meshing."""

    family: Family
    seed: int
    air: tuple[Box, ...]
    """Carved boxes; their union is the interior (free space before obstacles)."""
    solids: tuple[Solid, ...]
    """Obstacles inside the interior."""
    open_top: float | None
    """Z of the undrawn lid of an open family (its ceiling faces become barriers); None: closed."""
    seeds: np.ndarray  # (S, 3) float64 meters, free points with SEED_CLEARANCE around them

    @property
    def void(self) -> bool:
        """Every boundary face of the air is an undrawn barrier (a sky box on all sides, below included)."""
        return self.family == Family.FLOATING


# ---------------------------------------------------------------------------------------------
# Free-space tests (used for seeds, and by the tests to check them)


@dataclass(frozen=True)
class AirGrid:
    """The union of air boxes on the grid of their own coordinates (exact, no resampling)."""

    xs: np.ndarray  # (Nx + 1,) float64 sorted cell bounds
    ys: np.ndarray  # (Ny + 1,)
    zs: np.ndarray  # (Nz + 1,)
    air: np.ndarray  # (Nx, Ny, Nz) bool, True where the cell is inside some air box


def air_grid(boxes: Sequence[Box]) -> AirGrid:
    """Rasterise air boxes onto the grid of their distinct coordinates."""
    lo = np.array([b.lo for b in boxes], dtype=np.float64)  # (K, 3)
    hi = np.array([b.hi for b in boxes], dtype=np.float64)  # (K, 3)
    axes = [np.unique(np.concatenate([lo[:, a], hi[:, a]])) for a in range(3)]  # 3 × (N_a + 1,)
    air = np.zeros(tuple(len(x) - 1 for x in axes), dtype=bool)  # (Nx, Ny, Nz)
    start = [np.searchsorted(axes[a], lo[:, a]) for a in range(3)]  # 3 × (K,)
    stop = [np.searchsorted(axes[a], hi[:, a]) for a in range(3)]  # 3 × (K,)
    for k in range(len(boxes)):
        air[start[0][k] : stop[0][k], start[1][k] : stop[1][k], start[2][k] : stop[2][k]] = True
    return AirGrid(xs=axes[0], ys=axes[1], zs=axes[2], air=air)


def cubes_in_air(grid: AirGrid, points: np.ndarray, radius: float) -> np.ndarray:
    """Whether the cube of half-size radius about each point lies inside the air union: (S,) bool.

    Counts the air cells the cube overlaps with a summed-volume table and compares with the
    number of cells it overlaps.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)  # (S, 3)
    table = np.zeros(tuple(n + 1 for n in grid.air.shape), dtype=np.int64)  # (Nx + 1, Ny + 1, Nz + 1)
    table[1:, 1:, 1:] = grid.air.astype(np.int64).cumsum(0).cumsum(1).cumsum(2)
    inside = np.ones(len(points), dtype=bool)  # (S,)
    first, last = [], []
    for axis, bounds in enumerate((grid.xs, grid.ys, grid.zs)):
        lo, hi = points[:, axis] - radius, points[:, axis] + radius  # (S,) each
        inside &= (lo >= bounds[0]) & (hi <= bounds[-1])
        first.append(np.clip(np.searchsorted(bounds, lo, side="right") - 1, 0, len(bounds) - 1))  # (S,)
        last.append(np.clip(np.searchsorted(bounds, hi, side="left"), 0, len(bounds) - 1))  # (S,) exclusive
    (x0, y0, z0), (x1, y1, z1) = first, last
    count = (
        table[x1, y1, z1]
        - table[x0, y1, z1]
        - table[x1, y0, z1]
        - table[x1, y1, z0]
        + table[x0, y0, z1]
        + table[x0, y1, z0]
        + table[x1, y0, z0]
        - table[x0, y0, z0]
    )  # (S,) air cells overlapped
    return inside & (count == (x1 - x0) * (y1 - y0) * (z1 - z0))


def solid_distance(solid: Solid, points: np.ndarray) -> np.ndarray:
    """Euclidean distance from points (S, 3) to a solid (0 inside): (S,) float64."""
    shape = solid.shape
    if isinstance(shape, Box):
        gap = np.maximum(np.maximum(np.array(shape.lo) - points, points - np.array(shape.hi)), 0.0)  # (S, 3)
        return np.linalg.norm(gap, axis=1)
    if isinstance(shape, Slab):
        local = (points - np.array(shape.centre)) @ np.array(shape.axes).T  # (S, 3) in the slab's frame
        gap = np.maximum(np.abs(local) - np.array(shape.half), 0.0)  # (S, 3)
        return np.linalg.norm(gap, axis=1)
    radial = np.maximum(np.hypot(points[:, 0] - shape.x, points[:, 1] - shape.y) - shape.radius, 0.0)  # (S,)
    vertical = np.maximum(np.maximum(shape.z0 - points[:, 2], points[:, 2] - shape.z1), 0.0)  # (S,)
    return np.hypot(radial, vertical)


def solid_bounds(solid: Solid) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned bounds (lo (3,), hi (3,)) of a solid."""
    shape = solid.shape
    if isinstance(shape, Box):
        return np.array(shape.lo), np.array(shape.hi)
    if isinstance(shape, Slab):
        corners = shape.corners()  # (8, 3)
        return corners.min(axis=0), corners.max(axis=0)
    lo = np.array([shape.x - shape.radius, shape.y - shape.radius, shape.z0])
    return lo, np.array([shape.x + shape.radius, shape.y + shape.radius, shape.z1])


def is_clear(grid: AirGrid, solids: Sequence[Solid], points: np.ndarray, radius: float) -> np.ndarray:
    """Whether each point has `radius` of free space around it (inside the air, off every solid): (S,) bool."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)  # (S, 3)
    clear = cubes_in_air(grid, points, radius)  # (S,) bool
    for solid in solids:
        clear &= solid_distance(solid, points) > radius
    return clear


def _pick_seeds(
    rng: np.random.Generator,
    air: Sequence[Box],
    solids: Sequence[Solid],
    preferred: Sequence[Sequence[float]],
) -> np.ndarray:
    """Up to SEED_COUNT clear points: the preferred ones first, then random points in the air boxes."""
    grid = air_grid(air)
    chosen: list[np.ndarray] = []
    candidates = np.round(np.array(preferred, dtype=np.float64).reshape(-1, 3), 4)  # (P, 3)
    for point in candidates[is_clear(grid, solids, candidates, SEED_CLEARANCE)]:
        if len(chosen) < SEED_COUNT:
            chosen.append(point)
    lo = np.array([b.lo for b in air])  # (K, 3)
    hi = np.array([b.hi for b in air])  # (K, 3)
    volume = np.prod(hi - lo, axis=1)  # (K,)
    for _ in range(20):
        if len(chosen) >= SEED_COUNT:
            break
        pick = rng.choice(len(air), size=64, p=volume / volume.sum())  # (64,)
        z_top = np.minimum(hi[pick, 2], lo[pick, 2] + 2.5)  # (64,) keep seeds near flying height
        upper = np.column_stack([hi[pick, :2], z_top])  # (64, 3)
        points = np.round(rng.uniform(lo[pick], np.maximum(upper, lo[pick])), 4)  # (64, 3)
        for point in points[is_clear(grid, solids, points, SEED_CLEARANCE)]:
            if len(chosen) < SEED_COUNT:
                chosen.append(point)
    if not chosen:
        raise RuntimeError("procedural layout has no free point for a seed")
    return np.array(chosen, dtype=np.float64)  # (S, 3)


# ---------------------------------------------------------------------------------------------
# Families. Each returns (air boxes, solids, open_top, preferred seed points).

_Parts = tuple[list[Box], list[Solid], float | None, list[tuple[float, float, float]]]


def _box(x0: float, y0: float, z0: float, x1: float, y1: float, z1: float) -> Box:
    return Box((round(x0, 4), round(y0, 4), round(z0, 4)), (round(x1, 4), round(y1, 4), round(z1, 4)))


def _spanning_edges(
    rng: np.random.Generator, nx: int, ny: int, extra: float
) -> list[tuple[int, int, int, int]]:
    """Edges ((i, j), (i', j')) of a random spanning tree of an nx × ny grid, plus a fraction of extra edges."""
    edges = [(i, j, i + 1, j) for i in range(nx - 1) for j in range(ny)]
    edges += [(i, j, i, j + 1) for i in range(nx) for j in range(ny - 1)]
    order = rng.permutation(len(edges))
    parent = list(range(nx * ny))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    chosen = []
    for e in order:
        i, j, i2, j2 = edges[e]
        a, b = root(i * ny + j), root(i2 * ny + j2)
        if a != b:
            parent[a] = b
            chosen.append(edges[e])
        elif rng.random() < extra:
            chosen.append(edges[e])
    return sorted(chosen)


def _rooms(rng: np.random.Generator) -> _Parts:
    """A grid of rooms of varied sizes, separated by walls with doorways."""
    nx, ny = int(rng.integers(2, 5)), int(rng.integers(2, 4))
    wall = 0.3
    height = float(rng.uniform(2.8, 4.0))
    widths = rng.uniform(4.0, 9.0, nx)  # (nx,)
    depths = rng.uniform(4.0, 9.0, ny)  # (ny,)
    x0 = np.concatenate([[0.0], np.cumsum(widths + wall)])  # (nx + 1,) room starts
    y0 = np.concatenate([[0.0], np.cumsum(depths + wall)])  # (ny + 1,)
    air = [
        _box(x0[i], y0[j], 0.0, x0[i] + widths[i], y0[j] + depths[j], height)
        for i in range(nx)
        for j in range(ny)
    ]
    door_h = min(height - 0.3, float(rng.uniform(2.1, 2.6)))
    for i, j, i2, j2 in _spanning_edges(rng, nx, ny, 0.3):
        door_w = float(rng.uniform(1.2, 2.0))
        if i2 > i:  # door in the wall at x = x0[i] + widths[i], along y within room (i, j)
            c = float(rng.uniform(y0[j] + 0.3 + door_w / 2, y0[j] + depths[j] - 0.3 - door_w / 2))
            air.append(_box(x0[i] + widths[i], c - door_w / 2, 0.0, x0[i2], c + door_w / 2, door_h))
        else:
            c = float(rng.uniform(x0[i] + 0.3 + door_w / 2, x0[i] + widths[i] - 0.3 - door_w / 2))
            air.append(_box(c - door_w / 2, y0[j] + depths[j], 0.0, c + door_w / 2, y0[j2], door_h))
    solids: list[Solid] = []
    for i, j in itertools.product(range(nx), range(ny)):
        sx, sy, sz = rng.uniform(0.6, 1.2), rng.uniform(0.5, 1.2), rng.uniform(0.5, 1.2)
        if rng.random() < 0.6:  # a table or crate, 1.4 m or more from every wall (doorways stay clear)
            ax = float(rng.uniform(x0[i] + 1.4, x0[i] + widths[i] - 1.4 - sx))
            ay = float(rng.uniform(y0[j] + 1.4, y0[j] + depths[j] - 1.4 - sy))
            solids.append(Solid(_box(ax, ay, 0.0, ax + sx, ay + sy, sz), OBSTACLE))
    seed_z = min(2.0, height - 0.6)
    preferred = [(x0[i] + widths[i] / 2, y0[j] + depths[j] / 2, seed_z) for i in range(nx) for j in range(ny)]
    return air, solids, None, preferred


def _corridors(rng: np.random.Generator) -> _Parts:
    """A network of corridors on a grid of junctions, some junctions widened into small rooms."""
    nx, ny = int(rng.integers(3, 6)), int(rng.integers(3, 5))
    spacing = float(rng.uniform(6.0, 10.0))
    width = float(rng.uniform(1.6, 3.0))
    height = float(rng.uniform(2.5, 3.5))
    half = width / 2
    air: list[Box] = []
    preferred: list[tuple[float, float, float]] = []
    used = set()
    for i, j, i2, j2 in _spanning_edges(rng, nx, ny, 0.2):
        ax, ay, bx, by = i * spacing, j * spacing, i2 * spacing, j2 * spacing
        air.append(_box(ax - half, ay - half, 0.0, bx + half, by + half, height))
        preferred.append(((ax + bx) / 2, (ay + by) / 2, 1.4))
        used.update({(i, j), (i2, j2)})
    for i, j in sorted(used):
        if rng.random() < 0.3:
            r = float(rng.uniform(2.0, 3.5))
            h = float(rng.uniform(height, height + 2.0))
            air.append(_box(i * spacing - r, j * spacing - r, 0.0, i * spacing + r, j * spacing + r, h))
            preferred.insert(0, (i * spacing, j * spacing, 1.5))
    return air, [], None, preferred


def _hall(rng: np.random.Generator) -> _Parts:
    """A large hall with rows of pillars (round or square) and alcoves along its long walls."""
    length, width = float(rng.uniform(20.0, 45.0)), float(rng.uniform(12.0, 28.0))
    height = float(rng.uniform(6.0, 12.0))
    air = [_box(0.0, 0.0, 0.0, length, width, height)]
    for _ in range(int(rng.integers(0, 5))):
        w = float(rng.uniform(2.0, 5.0))
        x = float(rng.uniform(1.0, length - w - 1.0))
        depth = float(rng.uniform(1.5, 4.0))
        h = float(rng.uniform(3.0, height))
        air.append(
            _box(x, -depth, 0.0, x + w, 0.0, h)
            if rng.random() < 0.5
            else _box(x, width, 0.0, x + w, width + depth, h)
        )
    pitch = float(rng.uniform(4.0, 7.0))
    radius = float(rng.uniform(0.3, 0.8))
    round_pillars = rng.random() < 0.6
    xs = np.arange(pitch, length - pitch / 2, pitch)  # pillar columns
    ys = np.arange(pitch, width - pitch / 2, pitch)  # pillar rows
    solids = []
    for x, y in itertools.product(xs, ys):
        if round_pillars:
            solids.append(Solid(Cylinder(float(x), float(y), radius, 0.0, height), PILLAR))
        else:
            solids.append(Solid(_box(x - radius, y - radius, 0.0, x + radius, y + radius, height), PILLAR))
    centres = [(float(x + pitch / 2), float(y + pitch / 2)) for x, y in itertools.product(xs[:-1], ys[:-1])]
    preferred = [(x, y, z) for (x, y), z in itertools.product(centres, (1.5, height / 2))]
    preferred = [preferred[k] for k in rng.permutation(len(preferred))]
    return air, solids, None, preferred


def _maze(rng: np.random.Generator) -> _Parts:
    """A perfect maze (randomised depth-first search) on a grid of cells, with a few loops."""
    nx, ny = int(rng.integers(6, 13)), int(rng.integers(6, 13))
    cell = float(rng.uniform(2.0, 3.0))
    wall = 0.25
    height = float(rng.uniform(2.5, 3.5))
    inner = cell - wall
    air = [
        _box(i * cell, j * cell, 0.0, i * cell + inner, j * cell + inner, height)
        for i in range(nx)
        for j in range(ny)
    ]
    visited = np.zeros((nx, ny), dtype=bool)
    stack = [(0, 0)]
    visited[0, 0] = True
    links: list[tuple[int, int, int, int]] = []
    while stack:
        i, j = stack[-1]
        options = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        options = [(a, b) for a, b in options if 0 <= a < nx and 0 <= b < ny and not visited[a, b]]
        if not options:
            stack.pop()
            continue
        a, b = options[int(rng.integers(len(options)))]
        visited[a, b] = True
        links.append((min(i, a), min(j, b), max(i, a), max(j, b)))
        stack.append((a, b))
    extra = [(i, j, i + 1, j) for i in range(nx - 1) for j in range(ny)] + [
        (i, j, i, j + 1) for i in range(nx) for j in range(ny - 1)
    ]
    links += [e for e in extra if e not in links and rng.random() < 0.08]
    for i, j, i2, j2 in links:
        if i2 > i:
            air.append(_box(i * cell + inner, j * cell, 0.0, i2 * cell, j * cell + inner, height))
        else:
            air.append(_box(i * cell, j * cell + inner, 0.0, i * cell + inner, j2 * cell, height))
    order = rng.permutation(nx * ny)
    preferred = [((k // ny) * cell + inner / 2, (k % ny) * cell + inner / 2, 1.4) for k in order]
    return air, [], None, preferred


def _snap(value: float) -> float:
    return round(value * 4.0) / 4.0


def _caves(rng: np.random.Generator) -> _Parts:
    """Irregular chambers (clusters of overlapping boxes) joined by winding tunnels, on a 0.25 m grid."""
    count = int(rng.integers(3, 7))
    extent = float(rng.uniform(25.0, 45.0))
    centres: list[np.ndarray] = []
    while len(centres) < count:
        c = np.array([rng.uniform(0, extent), rng.uniform(0, extent), rng.uniform(0.0, 2.0)])
        if all(np.linalg.norm(c[:2] - o[:2]) > 8.0 for o in centres) or rng.random() < 0.02:
            centres.append(c)
    air: list[Box] = []
    preferred: list[tuple[float, float, float]] = []
    for c in centres:
        sx, sy, sz = rng.uniform(4.0, 9.0), rng.uniform(4.0, 9.0), rng.uniform(3.0, 6.0)
        air.append(
            _box(
                _snap(c[0] - sx / 2),
                _snap(c[1] - sy / 2),
                _snap(c[2]),
                _snap(c[0] + sx / 2),
                _snap(c[1] + sy / 2),
                _snap(c[2] + sz),
            )
        )
        for _ in range(int(rng.integers(2, 5))):
            off = rng.uniform(-0.5, 0.5, 3) * np.array([sx, sy, 0.0])
            bx, by, bz = rng.uniform(2.0, 5.0), rng.uniform(2.0, 5.0), rng.uniform(2.0, sz)
            lo = c + off - np.array([bx / 2, by / 2, -rng.uniform(-0.5, 1.0)])
            air.append(
                _box(
                    _snap(lo[0]),
                    _snap(lo[1]),
                    _snap(lo[2]),
                    _snap(lo[0] + bx),
                    _snap(lo[1] + by),
                    _snap(lo[2] + bz),
                )
            )
        preferred.append((_snap(c[0]) + 0.125, _snap(c[1]) + 0.125, _snap(c[2]) + 1.5))
    for k in range(1, count):
        target = centres[k]
        source = centres[int(np.argmin([np.linalg.norm(target[:2] - o[:2]) for o in centres[:k]]))]
        air += _tunnel(rng, source, target)
    return air, [], None, preferred


def _tunnel(rng: np.random.Generator, start: np.ndarray, end: np.ndarray) -> list[Box]:
    """Overlapping boxes along an L-shaped path (x first, then y) with lateral and vertical wander.

    Segments are at most 2 m long and overlap their neighbours by the tunnel width along the path;
    the wander per segment is small enough that consecutive cross-sections overlap by at least
    two thirds of the width and half of the height.
    """
    width, height = float(rng.uniform(1.6, 3.0)), float(rng.uniform(2.0, 3.0))
    legs = (
        (0, float(start[0]), float(end[0]), float(start[1])),
        (1, float(start[1]), float(end[1]), float(end[0])),
    )
    pieces = []
    for axis, a, b, base in legs:
        steps = max(1, int(np.ceil(abs(b - a) / 2.0)))
        pieces += [(axis, a + (b - a) * k / steps, a + (b - a) * (k + 1) / steps, base) for k in range(steps)]
    boxes: list[Box] = []
    lateral = 0.0
    rise = 0.0
    for k, (axis, t0, t1, base) in enumerate(pieces):
        if k and pieces[k - 1][0] != axis:
            lateral = 0.0
        lateral = float(np.clip(lateral + rng.uniform(-width / 6, width / 6), -width / 3, width / 3))
        rise = float(np.clip(rise + rng.uniform(-height / 8, height / 8), -height / 4, height / 4))
        floor = float(start[2] + (end[2] - start[2]) * (k + 1) / len(pieces)) + rise
        lo, hi = [0.0, 0.0, floor], [0.0, 0.0, floor + height]
        lo[axis], hi[axis] = min(t0, t1) - width / 2, max(t0, t1) + width / 2
        lo[1 - axis], hi[1 - axis] = base + lateral - width / 2, base + lateral + width / 2
        boxes.append(_box(*(_snap(v) for v in lo), *(_snap(v) for v in hi)))
    return boxes


def _forest(rng: np.random.Generator) -> _Parts:
    """A fenced clearing of tree trunks and boulders under an open (undrawn) sky."""
    length, width = float(rng.uniform(20.0, 50.0)), float(rng.uniform(20.0, 50.0))
    height = float(rng.uniform(8.0, 14.0))
    spacing = float(rng.uniform(2.2, 3.5))
    solids: list[Solid] = []
    placed: list[tuple[float, float, float]] = []
    for _ in range(int(length * width / spacing**2) * 2):
        x, y, r = (
            float(rng.uniform(0.6, length - 0.6)),
            float(rng.uniform(0.6, width - 0.6)),
            float(rng.uniform(0.15, 0.5)),
        )
        if all(np.hypot(x - px, y - py) > spacing + r + pr for px, py, pr in placed):
            placed.append((x, y, r))
            solids.append(Solid(Cylinder(x, y, r, 0.0, height), TRUNK))
    for _ in range(int(rng.integers(2, 8))):
        x, y, s = (
            float(rng.uniform(1.0, length - 2.0)),
            float(rng.uniform(1.0, width - 2.0)),
            float(rng.uniform(0.5, 1.5)),
        )
        if all(np.hypot(x - px, y - py) > s + pr + 1.4 for px, py, pr in placed):
            placed.append((x, y, s))
            solids.append(
                Solid(
                    _box(x - s / 2, y - s / 2, 0.0, x + s / 2, y + s / 2, float(rng.uniform(0.4, 1.2))),
                    OBSTACLE,
                )
            )
    return [_box(0.0, 0.0, 0.0, length, width, height)], solids, height, []


def _building(rng: np.random.Generator) -> _Parts:
    """A multi-storey building: rooms per floor, slabs with stairwell openings and steps."""
    floors = int(rng.integers(2, 5))
    length, width = float(rng.uniform(12.0, 28.0)), float(rng.uniform(10.0, 20.0))
    storey, slab, wall = float(rng.uniform(3.0, 3.6)), 0.3, 0.25
    air: list[Box] = []
    solids: list[Solid] = []
    preferred: list[tuple[float, float, float]] = []
    for f in range(floors):
        z0 = f * (storey + slab)
        rooms = int(rng.integers(1, 4))
        spans = 3.0 + rng.dirichlet(np.ones(rooms)) * (length - 3.0 * rooms)  # (rooms,) each >= 3 m
        cuts = np.cumsum(spans)[:-1]  # (rooms - 1,) wall centre lines
        starts = np.concatenate([[0.0], cuts + wall / 2])  # (rooms,)
        ends = np.concatenate([cuts - wall / 2, [length]])  # (rooms,)
        for a, b in zip(starts, ends, strict=True):
            air.append(_box(a, 0.0, z0, b, width, z0 + storey))
            preferred.append(((a + b) / 2, width / 2, z0 + 1.5))
        for cut in cuts:
            door_w = float(rng.uniform(1.2, 2.2))
            c = float(rng.uniform(0.4 + door_w / 2, width - 0.4 - door_w / 2))
            air.append(
                _box(
                    cut - wall / 2,
                    c - door_w / 2,
                    z0,
                    cut + wall / 2,
                    c + door_w / 2,
                    z0 + min(2.4, storey - 0.2),
                )
            )
        if f + 1 < floors:  # stairwell: an opening through the slab above, steps along half of it
            hole_l, hole_w = float(rng.uniform(3.5, 5.0)), float(rng.uniform(2.4, 3.2))
            hx = float(rng.uniform(0.5, length - hole_l - 0.5))
            hy = 0.0 if rng.random() < 0.5 else width - hole_w
            air.append(_box(hx, hy, z0 + storey, hx + hole_l, hy + hole_w, (f + 1) * (storey + slab)))
            steps = int(np.ceil(storey / 0.4))
            for s in range(steps - 3):
                run = hole_l / steps
                solids.append(
                    Solid(
                        _box(
                            hx + s * run,
                            hy,
                            z0,
                            hx + (s + 1) * run,
                            hy + hole_w / 2,
                            z0 + (s + 1) * storey / steps,
                        ),
                        STAIRS,
                    )
                )
    return air, solids, None, preferred


def _yard(rng: np.random.Generator) -> _Parts:
    """A walled yard under an open sky with crates, containers, barrels and low walls."""
    length, width = float(rng.uniform(20.0, 55.0)), float(rng.uniform(20.0, 55.0))
    height = float(rng.uniform(5.0, 9.0))
    solids: list[Solid] = []
    footprints: list[tuple[float, float, float, float]] = []
    for _ in range(int(length * width / 25)):
        kind = rng.random()
        if kind < 0.45:
            sx, sy, sz = rng.uniform(1.0, 6.0), rng.uniform(1.0, 3.0), rng.uniform(1.0, 4.0)
        elif kind < 0.7:
            sx, sy, sz = rng.uniform(0.3, 0.4), rng.uniform(3.0, 8.0), rng.uniform(1.0, 2.5)
        else:
            r = float(rng.uniform(0.3, 2.0))
            sx = sy = 2 * r
            sz = float(rng.uniform(1.0, 4.0))
        if rng.random() < 0.5:
            sx, sy = sy, sx
        x, y = float(rng.uniform(0.0, length - sx)), float(rng.uniform(0.0, width - sy))
        gap = 1.4
        if any(
            x < fx1 + gap and fx0 < x + sx + gap and y < fy1 + gap and fy0 < y + sy + gap
            for fx0, fy0, fx1, fy1 in footprints
        ):
            continue
        footprints.append((x, y, x + sx, y + sy))
        if kind >= 0.7:
            solids.append(Solid(Cylinder(x + sx / 2, y + sy / 2, sx / 2, 0.0, float(sz)), OBSTACLE))
        else:
            solids.append(Solid(_box(x, y, 0.0, x + sx, y + sy, sz), OBSTACLE))
    return [_box(0.0, 0.0, 0.0, length, width, height)], solids, height, []


class _Ground:
    """Footprints (x0, y0, x1, y1) reserved on a floor, so that what stands on it keeps GAP apart."""

    GAP = 1.4

    def __init__(self, rng: np.random.Generator, lo: tuple[float, float], hi: tuple[float, float]) -> None:
        self.rng, self.lo, self.hi = rng, lo, hi
        self.taken: list[tuple[float, float, float, float]] = []

    def free(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        inside = self.lo[0] <= x0 and self.lo[1] <= y0 and x1 <= self.hi[0] and y1 <= self.hi[1]
        g = self.GAP
        return inside and not any(
            x0 < b[2] + g and b[0] < x1 + g and y0 < b[3] + g and b[1] < y1 + g for b in self.taken
        )

    def place(self, sx: float, sy: float, margin: float = 1.0, tries: int = 40) -> tuple[float, float] | None:
        """The lower corner of a free sx × sy footprint at least `margin` from the edges (reserved), or None."""
        for _ in range(tries):
            x = float(
                self.rng.uniform(self.lo[0] + margin, max(self.lo[0] + margin, self.hi[0] - margin - sx))
            )
            y = float(
                self.rng.uniform(self.lo[1] + margin, max(self.lo[1] + margin, self.hi[1] - margin - sy))
            )
            if self.free(x, y, x + sx, y + sy):
                self.taken.append((x, y, x + sx, y + sy))
                return x, y
        return None


def _ramp_run(rise: float, rng: np.random.Generator, longest: float) -> float | None:
    """The horizontal run of a ramp climbing `rise` meters at 15-32 degrees, at most `longest` (None: too
    steep then, above 40 degrees)."""
    run = rise / np.tan(np.radians(rng.uniform(15.0, 32.0)))
    run = min(float(run), longest)
    return run if run > 0 and np.degrees(np.arctan2(rise, run)) <= 40.0 else None


def _arena(rng: np.random.Generator) -> _Parts:
    """A deathmatch arena: a tall atrium with balconies behind railings, ramps up to them, thick and thin
    pillars, slanted struts, ledges and jump-pad pedestals, and doorways to corridors and side rooms."""
    length, width = float(rng.uniform(22.0, 40.0)), float(rng.uniform(16.0, 30.0))
    height = float(rng.uniform(8.0, 18.0))
    air = [_box(0.0, 0.0, 0.0, length, width, height)]
    solids: list[Solid] = []
    preferred = [(length / 2, width / 2, 1.5), (length / 2, width / 2, height / 2)]
    ground = _Ground(rng, (0.0, 0.0), (length, width))
    deck = float(rng.uniform(3.5, min(6.0, height - 3.0)))  # top of the balconies' floor
    depth = float(rng.uniform(3.0, 5.0))
    for side in (0,) if rng.random() < 0.5 else (0, 1):
        y0, y1 = (0.0, depth) if side == 0 else (width - depth, width)
        edge = y1 if side == 0 else y0  # the balcony's open edge
        inward = 1.0 if side == 0 else -1.0  # from the edge into the atrium
        solids.append(Solid(_box(0.0, y0, deck - 0.4, length, y1, deck), FLOOR))
        preferred.append((length / 2, (y0 + y1) / 2, deck + 1.5))
        gap = None  # x range of the railing left open where the ramp arrives
        rw = float(rng.uniform(2.0, 3.2))
        run = _ramp_run(deck, rng, width - 2 * depth - 2.0)
        if run is not None:
            xr = float(rng.uniform(2.0 + rw / 2, length - 2.0 - rw / 2))
            foot = (xr - rw / 2, min(edge, edge + inward * run), xr + rw / 2, max(edge, edge + inward * run))
            if ground.free(*foot):
                ground.taken.append(foot)
                solids.append(
                    Solid(slab_between((xr, edge + inward * run, 0.0), (xr, edge, deck), rw, 0.3), RAMP)
                )
                gap = (xr - rw / 2 - 0.2, xr + rw / 2 + 0.2)
        post_r, pitch = float(rng.uniform(0.05, 0.1)), float(rng.uniform(1.2, 2.0))
        rail_y = edge - inward * 0.15
        spans = [(0.0, length)] if gap is None else [(0.0, gap[0]), (gap[1], length)]
        for a, b in spans:
            if b - a < 0.5:
                continue
            for x in np.arange(a + 0.2, b - 0.1, pitch):
                solids.append(Solid(Cylinder(float(x), rail_y, post_r, deck, deck + 1.0), RAILING))
            solids.append(Solid(_box(a, rail_y - 0.05, deck + 0.95, b, rail_y + 0.05, deck + 1.05), RAILING))
    for _ in range(int(rng.integers(3, 11))):  # pillars, thick or thin, round or square
        r = float(rng.uniform(0.4, 0.9)) if rng.random() < 0.5 else float(rng.uniform(0.1, 0.25))
        spot = ground.place(2 * r, 2 * r)
        if spot is not None:
            x, y = spot[0] + r, spot[1] + r
            top = height if rng.random() < 0.7 else float(rng.uniform(1.0, height - 2.0))
            shape = (
                Cylinder(x, y, r, 0.0, top)
                if rng.random() < 0.6
                else _box(x - r, y - r, 0.0, x + r, y + r, top)
            )
            solids.append(Solid(shape, PILLAR))
    for _ in range(int(rng.integers(0, 4))):  # slanted struts leaning across the air
        reach, rise = float(rng.uniform(1.5, 4.0)), float(rng.uniform(2.5, min(6.0, height - 1.0)))
        spot = ground.place(reach, 0.6)
        if spot is not None:
            x, y = spot[0], spot[1] + 0.3
            low, high = (x, y, 0.0), (x + reach, y, rise)
            solids.append(
                Solid(slab_between(low, high, float(rng.uniform(0.2, 0.4)), 0.3, top=False), OBSTACLE)
            )
    for _ in range(int(rng.integers(1, 4))):  # ledges and jump-pad pedestals
        if rng.random() < 0.5:
            sx, sy = float(rng.uniform(2.5, 6.0)), float(rng.uniform(2.5, 6.0))
            spot = ground.place(sx, sy)
            if spot is not None:
                top = float(rng.uniform(0.8, 2.5))
                solids.append(Solid(_box(spot[0], spot[1], 0.0, spot[0] + sx, spot[1] + sy, top), OBSTACLE))
                preferred.append((spot[0] + sx / 2, spot[1] + sy / 2, top + 1.5))
        else:
            r = float(rng.uniform(0.6, 1.0))
            spot = ground.place(2 * r, 2 * r)
            if spot is not None:
                pad = Cylinder(spot[0] + r, spot[1] + r, r, 0.0, float(rng.uniform(0.15, 0.35)))
                solids.append(Solid(pad, OBSTACLE))
    room = 58.0 - length  # meters left along x for corridors and rooms at the two ends
    for end in (0, 1) if rng.random() < 0.6 else (int(rng.integers(0, 2)),):
        door_w, door_h = float(rng.uniform(1.4, 2.2)), float(rng.uniform(2.2, min(2.8, deck - 0.5)))
        hall_w, hall_h = float(rng.uniform(door_w, 3.5)), float(rng.uniform(door_h + 0.2, deck - 0.4))
        long_ = float(rng.uniform(3.0, max(3.0, room / 2 - 6.0)))
        r = float(rng.uniform(2.0, max(2.0, min(4.0, (room / 2 - long_ - 0.3) / 2))))
        c = (
            float(rng.uniform(depth + r + 0.5, width - depth - r - 0.5))
            if width - 2 * depth > 2 * r + 1
            else width / 2
        )
        sign, wall_x = (1.0, length) if end == 1 else (-1.0, 0.0)
        xs = [
            wall_x,
            wall_x + sign * 0.3,
            wall_x + sign * (0.3 + long_),
            wall_x + sign * (0.3 + long_ + 2 * r),
        ]
        air.append(_box(min(xs[0], xs[1]), c - door_w / 2, 0.0, max(xs[0], xs[1]), c + door_w / 2, door_h))
        air.append(_box(min(xs[1], xs[2]), c - hall_w / 2, 0.0, max(xs[1], xs[2]), c + hall_w / 2, hall_h))
        air.append(_box(min(xs[2], xs[3]), c - r, 0.0, max(xs[2], xs[3]), c + r, min(height, hall_h + 1.5)))
        preferred.append(((xs[1] + xs[2]) / 2, c, 1.4))
        preferred.append(((xs[2] + xs[3]) / 2, c, 1.5))
    return air, solids, None, preferred


def _platforms(rng: np.random.Generator) -> _Parts:
    """Open-air platforms on posts at several heights with ramps up to them, slanted struts, thin poles,
    low walls and arches, under an open sky."""
    length, width = float(rng.uniform(24.0, 56.0)), float(rng.uniform(24.0, 56.0))
    height = float(rng.uniform(10.0, 22.0))
    solids: list[Solid] = []
    preferred: list[tuple[float, float, float]] = []
    ground = _Ground(rng, (0.0, 0.0), (length, width))
    for _ in range(int(np.clip(length * width / 250.0, 2, 6))):
        sx, sy = float(rng.uniform(4.0, 10.0)), float(rng.uniform(4.0, 10.0))
        deck = float(rng.uniform(2.4, min(8.0, height - 3.0)))
        run = _ramp_run(deck, rng, 14.0)
        rw = float(rng.uniform(1.8, 3.0))
        along_x = rng.random() < 0.5
        full = (sx + (run or 0.0), sy) if along_x else (sx, sy + (run or 0.0))
        spot = ground.place(*full)
        if spot is None:
            continue
        x0, y0 = spot
        px, py = (x0 + (run or 0.0), y0) if along_x else (x0, y0 + (run or 0.0))  # the platform's corner
        solids.append(Solid(_box(px, py, deck - 0.4, px + sx, py + sy, deck), FLOOR))
        post = float(rng.uniform(0.12, 0.3))
        for cx, cy in itertools.product((px + 0.4, px + sx - 0.4), (py + 0.4, py + sy - 0.4)):
            solids.append(Solid(Cylinder(cx, cy, post, 0.0, deck - 0.4), PILLAR))
        if run is not None:
            if along_x:
                c = float(rng.uniform(py + rw / 2, py + sy - rw / 2))
                solids.append(Solid(slab_between((x0, c, 0.0), (px, c, deck), rw, 0.3), RAMP))
            else:
                c = float(rng.uniform(px + rw / 2, px + sx - rw / 2))
                solids.append(Solid(slab_between((c, y0, 0.0), (c, py, deck), rw, 0.3), RAMP))
        preferred.append((px + sx / 2, py + sy / 2, deck + 1.5))
        if deck - 0.4 >= 2.2:
            preferred.append((px + sx / 2, py + sy / 2, (deck - 0.4) / 2))
    for _ in range(int(rng.integers(4, 15))):  # thin poles
        r = float(rng.uniform(0.06, 0.15))
        spot = ground.place(2 * r, 2 * r, margin=0.6)
        if spot is not None:
            pole = Cylinder(spot[0] + r, spot[1] + r, r, 0.0, float(rng.uniform(3.0, min(7.0, height - 1.0))))
            solids.append(Solid(pole, PILLAR))
    for _ in range(int(rng.integers(2, 6))):  # slanted struts
        reach, rise = float(rng.uniform(2.0, 5.0)), float(rng.uniform(3.0, 6.0))
        spot = ground.place(reach, 0.6)
        if spot is not None:
            foot, head = (spot[0], spot[1] + 0.3, 0.0), (spot[0] + reach, spot[1] + 0.3, rise)
            solids.append(
                Solid(slab_between(foot, head, float(rng.uniform(0.2, 0.5)), 0.3, top=False), OBSTACLE)
            )
    for _ in range(int(rng.integers(2, 7))):  # low walls
        lw, th, tall = (
            float(rng.uniform(2.0, 8.0)),
            float(rng.uniform(0.2, 0.3)),
            float(rng.uniform(0.8, 1.5)),
        )
        sx, sy = (lw, th) if rng.random() < 0.5 else (th, lw)
        spot = ground.place(sx, sy)
        if spot is not None:
            solids.append(Solid(_box(spot[0], spot[1], 0.0, spot[0] + sx, spot[1] + sy, tall), WALL))
    for _ in range(int(rng.integers(0, 3))):  # arches: two piers and a lintel
        span, pier, top = (
            float(rng.uniform(2.5, 5.0)),
            float(rng.uniform(0.4, 0.8)),
            float(rng.uniform(3.0, 5.0)),
        )
        spot = ground.place(span + 2 * pier, pier)
        if spot is not None:
            x, y = spot
            solids.append(Solid(_box(x, y, 0.0, x + pier, y + pier, top), WALL))
            solids.append(Solid(_box(x + pier + span, y, 0.0, x + 2 * pier + span, y + pier, top), WALL))
            solids.append(Solid(_box(x, y, top, x + 2 * pier + span, y + pier, top + 0.6), WALL))
    return [_box(0.0, 0.0, 0.0, length, width, height)], solids, height, preferred


def _floating(rng: np.random.Generator) -> _Parts:
    """A space map: floating decks at many heights in a sky box (undrawn on every side, below included),
    bridges and ramps between them with thin side rails, roofs on posts over some decks, towers from the
    bottom to the sky, hanging and standing poles, slanted struts and jump-pad pedestals."""
    length, width = float(rng.uniform(40.0, 80.0)), float(rng.uniform(30.0, 60.0))
    height = float(rng.uniform(22.0, 40.0))
    solids: list[Solid] = []
    preferred: list[tuple[float, float, float]] = []
    decks: list[tuple[float, float, float, float, float]] = []  # (x0, y0, x1, y1, top)

    def clear_of_decks(x0: float, y0: float, z0: float, x1: float, y1: float, z1: float, gap: float) -> bool:
        return not any(
            x0 < d[2] + gap
            and d[0] < x1 + gap
            and y0 < d[3] + gap
            and d[1] < y1 + gap
            and z0 < d[4] + gap + 3.0
            and d[4] - 1.6 < z1 + gap
            for d in decks
        )

    for _ in range(int(np.clip(length * width / 220.0, 5, 12))):  # decks, some over others
        for _try in range(30):
            sx, sy = float(rng.uniform(5.0, 14.0)), float(rng.uniform(5.0, 14.0))
            x0 = float(rng.uniform(2.0, length - 2.0 - sx))
            y0 = float(rng.uniform(2.0, width - 2.0 - sy))
            top = float(rng.uniform(3.0, height - 6.0))
            thick = float(rng.uniform(0.4, 1.6))
            if clear_of_decks(x0, y0, top - thick, x0 + sx, y0 + sy, top, 1.5):
                decks.append((x0, y0, x0 + sx, y0 + sy, top))
                solids.append(Solid(_box(x0, y0, top - thick, x0 + sx, y0 + sy, top), FLOOR))
                preferred.append((x0 + sx / 2, y0 + sy / 2, top + 1.5))
                if rng.random() < 0.35:  # a column under the deck down to the bottom of the box
                    r = float(rng.uniform(0.5, 1.5))
                    solids.append(Solid(Cylinder(x0 + sx / 2, y0 + sy / 2, r, 0.0, top - thick), PILLAR))
                else:
                    preferred.append((x0 + sx / 2, y0 + sy / 2, top - thick - 1.5))
                break
    for a, b in itertools.pairwise(decks):  # bridges and ramps from deck to deck
        pa = np.array([(a[0] + a[2]) / 2, (a[1] + a[3]) / 2, a[4]])  # (3,) deck centres on top
        pb = np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2, b[4]])  # (3,)
        run = float(np.hypot(*(pb - pa)[:2]))
        if run < 4.0 or np.degrees(np.arctan2(abs(pb[2] - pa[2]), run)) > 30.0 or rng.random() < 0.25:
            continue
        bw = float(rng.uniform(1.6, 3.0))
        solids.append(Solid(slab_between(pa.tolist(), pb.tolist(), bw, 0.3), RAMP))
        if rng.random() < 0.6:  # thin rails along both sides, a meter above the walking surface
            along = (pb - pa) / np.linalg.norm(pb - pa)  # (3,)
            side = np.cross([0.0, 0.0, 1.0], along)  # (3,)
            side /= np.linalg.norm(side)
            thick = float(rng.uniform(0.06, 0.12))
            for sign in (-1.0, 1.0):
                off = side * sign * (bw / 2 - thick) + np.array([0.0, 0.0, 1.0])  # (3,)
                solids.append(Solid(slab_between(pa + off, pb + off, thick, thick, top=False), RAILING))
    for d in decks:  # roofs on posts over some decks: low ceilings in the open
        if rng.random() < 0.35 and d[4] + 4.5 < height - 1.0:
            roof = d[4] + float(rng.uniform(2.6, 4.0))
            x0, y0, x1, y1 = d[0] + 0.5, d[1] + 0.5, d[2] - 0.5, d[3] - 0.5
            solids.append(Solid(_box(x0, y0, roof, x1, y1, roof + 0.3), FLOOR))
            post = float(rng.uniform(0.1, 0.3))
            for cx, cy in itertools.product((x0 + post, x1 - post), (y0 + post, y1 - post)):
                solids.append(Solid(Cylinder(cx, cy, post, d[4], roof), PILLAR))
        elif rng.random() < 0.5:  # a jump-pad pedestal or a low wall on the deck
            if rng.random() < 0.5:
                r = float(rng.uniform(0.6, 1.0))
                cx, cy = (d[0] + d[2]) / 2 + float(rng.uniform(-1.0, 1.0)), (d[1] + d[3]) / 2
                solids.append(
                    Solid(Cylinder(cx, cy, r, d[4], d[4] + float(rng.uniform(0.15, 0.35))), OBSTACLE)
                )
            else:
                tall = float(rng.uniform(0.8, 1.5))
                solids.append(Solid(_box(d[0], d[1], d[4], d[2], d[1] + 0.3, d[4] + tall), WALL))
    for _ in range(int(rng.integers(2, 6))):  # towers from the bottom to the sky
        for _try in range(20):
            r = float(rng.uniform(1.0, 4.0))
            x, y = float(rng.uniform(r + 1.0, length - r - 1.0)), float(rng.uniform(r + 1.0, width - r - 1.0))
            if clear_of_decks(x - r, y - r, 0.0, x + r, y + r, height, 1.5):
                square = _box(x - r, y - r, 0.0, x + r, y + r, height)
                solids.append(Solid(Cylinder(x, y, r, 0.0, height) if rng.random() < 0.5 else square, WALL))
                break
    for _ in range(int(rng.integers(4, 12))):  # poles hanging from the sky or standing on the bottom
        r = float(rng.uniform(0.06, 0.2))
        x, y = float(rng.uniform(1.0, length - 1.0)), float(rng.uniform(1.0, width - 1.0))
        span = float(rng.uniform(4.0, height * 0.6))
        z0, z1 = (height - span, height) if rng.random() < 0.5 else (0.0, span)
        if clear_of_decks(x - r, y - r, z0, x + r, y + r, z1, 1.4):
            solids.append(Solid(Cylinder(x, y, r, z0, z1), PILLAR))
    for _ in range(int(rng.integers(2, 6))):  # slanted struts leaning across the air
        x, y, z = (
            float(rng.uniform(2.0, length - 6.0)),
            float(rng.uniform(2.0, width - 2.0)),
            float(rng.uniform(1.0, height - 8.0)),
        )
        reach, rise = float(rng.uniform(2.0, 5.0)), float(rng.uniform(3.0, 6.0))
        if clear_of_decks(x, y - 0.3, z, x + reach, y + 0.3, z + rise, 1.4):
            beam = slab_between(
                (x, y, z), (x + reach, y, z + rise), float(rng.uniform(0.2, 0.4)), 0.3, top=False
            )
            solids.append(Solid(beam, OBSTACLE))
    for _ in range(8):  # open air between the decks
        preferred.append(
            (
                float(rng.uniform(2.0, length - 2.0)),
                float(rng.uniform(2.0, width - 2.0)),
                float(rng.uniform(3.0, height - 3.0)),
            )
        )
    return [_box(0.0, 0.0, 0.0, length, width, height)], solids, height, preferred


def _field(rng: np.random.Generator) -> _Parts:
    """A wide field under a high sky: a floor 60-140 m across, walled far away, and a few landmarks at
    least FIELD_GAP apart (towers up to the sky, pillars, blocks of buildings, plateaus with a ramp up,
    long low walls, thin poles), so that most of the air is clear for 10 m all round and the floor is
    often the only surface in range, as in the open parts of large real maps. Seeds lie 1-12 m up."""
    length, width = float(rng.uniform(60.0, 140.0)), float(rng.uniform(60.0, 140.0))
    height = float(rng.uniform(14.0, 40.0))
    solids: list[Solid] = []
    preferred: list[tuple[float, float, float]] = []
    ground = _Ground(rng, (0.0, 0.0), (length, width))

    def spot(sx: float, sy: float) -> tuple[float, float] | None:
        """The lower corner of an sx × sy footprint with FIELD_GAP of open floor reserved round it."""
        corner = ground.place(sx + 2 * FIELD_GAP, sy + 2 * FIELD_GAP, margin=0.0)
        return None if corner is None else (corner[0] + FIELD_GAP, corner[1] + FIELD_GAP)

    for _ in range(int(np.clip(length * width / 1200.0, 4, 12))):
        kind = rng.random()
        if kind < 0.2:  # a tower up to the sky
            r = float(rng.uniform(1.0, 4.0))
            at = spot(2 * r, 2 * r)
            if at is not None:
                x, y = at[0] + r, at[1] + r
                square = _box(x - r, y - r, 0.0, x + r, y + r, height)
                solids.append(Solid(Cylinder(x, y, r, 0.0, height) if rng.random() < 0.5 else square, WALL))
        elif kind < 0.4:  # a pillar or a thin pole
            r = float(rng.uniform(0.3, 1.0)) if rng.random() < 0.6 else float(rng.uniform(0.06, 0.15))
            at = spot(2 * r, 2 * r)
            if at is not None:
                top = float(rng.uniform(3.0, height - 1.0))
                solids.append(Solid(Cylinder(at[0] + r, at[1] + r, r, 0.0, top), PILLAR))
        elif kind < 0.6:  # a block of buildings
            sx, sy, tall = (
                float(rng.uniform(4.0, 14.0)),
                float(rng.uniform(4.0, 14.0)),
                float(rng.uniform(3.0, 10.0)),
            )
            at = spot(sx, sy)
            if at is not None:
                solids.append(
                    Solid(_box(at[0], at[1], 0.0, at[0] + sx, at[1] + sy, min(tall, height - 2.0)), WALL)
                )
        elif kind < 0.8:  # a plateau with a ramp up to it
            sx, sy, top = (
                float(rng.uniform(8.0, 18.0)),
                float(rng.uniform(8.0, 18.0)),
                float(rng.uniform(1.5, 4.0)),
            )
            run = _ramp_run(top, rng, 12.0)
            rw = float(rng.uniform(2.0, 3.5))
            at = spot(sx + (run or 0.0), sy)
            if at is not None:
                px = at[0] + (run or 0.0)
                solids.append(Solid(_box(px, at[1], 0.0, px + sx, at[1] + sy, top), FLOOR))
                if run is not None:
                    c = float(rng.uniform(at[1] + rw / 2, at[1] + sy - rw / 2))
                    solids.append(Solid(slab_between((at[0], c, 0.0), (px, c, top), rw, 0.3), RAMP))
                preferred.append((px + sx / 2, at[1] + sy / 2, top + float(rng.uniform(1.0, 6.0))))
        else:  # a long low wall
            lw, th, tall = (
                float(rng.uniform(6.0, 20.0)),
                float(rng.uniform(0.25, 0.5)),
                float(rng.uniform(1.0, 2.5)),
            )
            sx, sy = (lw, th) if rng.random() < 0.5 else (th, lw)
            at = spot(sx, sy)
            if at is not None:
                solids.append(Solid(_box(at[0], at[1], 0.0, at[0] + sx, at[1] + sy, tall), WALL))
    for _ in range(10):  # open air at every height a drone flies
        preferred.append(
            (
                float(rng.uniform(2.0, length - 2.0)),
                float(rng.uniform(2.0, width - 2.0)),
                float(rng.uniform(1.0, min(12.0, height - 2.0))),
            )
        )
    return [_box(0.0, 0.0, 0.0, length, width, height)], solids, height, preferred


FIELD_GAP = 8.0
"""Meters of open floor the field family keeps round each landmark."""


def build_layout(family: Family | str, seed: int) -> Layout:
    """The primitives of one scene of a family; the same (family, seed) always gives the same layout."""
    fam = Family(family)
    rng = np.random.default_rng(np.random.SeedSequence([FAMILIES.index(fam), seed]))
    match fam:
        case Family.ROOMS:
            parts = _rooms(rng)
        case Family.CORRIDORS:
            parts = _corridors(rng)
        case Family.HALL:
            parts = _hall(rng)
        case Family.MAZE:
            parts = _maze(rng)
        case Family.CAVES:
            parts = _caves(rng)
        case Family.FOREST:
            parts = _forest(rng)
        case Family.BUILDING:
            parts = _building(rng)
        case Family.YARD:
            parts = _yard(rng)
        case Family.ARENA:
            parts = _arena(rng)
        case Family.PLATFORMS:
            parts = _platforms(rng)
        case Family.FLOATING:
            parts = _floating(rng)
        case Family.FIELD:
            parts = _field(rng)
    air, solids, open_top, preferred = parts
    seeds = _pick_seeds(rng, air, solids, preferred)
    return Layout(family=fam, seed=seed, air=tuple(air), solids=tuple(solids), open_top=open_top, seeds=seeds)


# ---------------------------------------------------------------------------------------------
# Meshing


def _air_quads(grid: AirGrid) -> tuple[np.ndarray, np.ndarray]:
    """Boundary of the air union as quads facing into the air, merged into runs along one axis.

    Returns (corners (Q, 4, 3) float64 counter-clockwise seen from the air, normal axis × sign (Q,) int64
    in {±1, ±2, ±3}).
    """
    bounds = (grid.xs, grid.ys, grid.zs)
    quads: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    for axis in range(3):
        b_axis, c_axis = (axis + 1) % 3, (axis + 2) % 3
        occ = np.moveaxis(grid.air, (axis, b_axis, c_axis), (0, 1, 2))  # (Na, Nb, Nc)
        padded = np.pad(occ, ((1, 1), (0, 0), (0, 0)))  # (Na + 2, Nb, Nc)
        below, above = padded[:-1], padded[1:]  # (Na + 1, Nb, Nc) cells on either side of each plane
        for sign, mask in ((+1, ~below & above), (-1, below & ~above)):
            prev = np.pad(mask, ((0, 0), (0, 0), (1, 0)))[:, :, :-1]  # (Na + 1, Nb, Nc)
            nxt = np.pad(mask, ((0, 0), (0, 0), (0, 1)))[:, :, 1:]  # (Na + 1, Nb, Nc)
            t, j, k0 = np.nonzero(mask & ~prev)  # (Q,) run starts
            _, _, k1 = np.nonzero(mask & ~nxt)  # (Q,) run ends (same order)
            a = bounds[axis][t]  # (Q,)
            b0, b1 = bounds[b_axis][j], bounds[b_axis][j + 1]  # (Q,)
            c0, c1 = bounds[c_axis][k0], bounds[c_axis][k1 + 1]  # (Q,)
            corner = np.zeros((len(t), 4, 3))  # (Q, 4, 3)
            corner[:, :, axis] = a[:, None]
            corner[:, :, b_axis] = np.stack([b0, b1, b1, b0], axis=1)
            corner[:, :, c_axis] = np.stack([c0, c0, c1, c1], axis=1)
            if sign < 0:
                corner = corner[:, ::-1]
            quads.append(corner)
            normals.append(np.full(len(t), sign * (axis + 1), dtype=np.int64))
    return np.concatenate(quads), np.concatenate(normals)


def _box_quads(box: Box) -> np.ndarray:
    """The 6 faces of a box, counter-clockwise seen from outside: (6, 4, 3)."""
    lo, hi = np.array(box.lo), np.array(box.hi)
    corner = np.array(list(itertools.product((0, 1), repeat=3)))  # (8, 3) bits (x, y, z)
    pts = lo + corner * (hi - lo)  # (8, 3)
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return pts[np.array(faces)]  # (6, 4, 3)


def _cylinder_triangles(c: Cylinder) -> np.ndarray:
    """Side and caps of a vertical cylinder, counter-clockwise seen from outside: (4·segments, 3, 3)."""
    angle = np.linspace(0.0, 2 * np.pi, CYLINDER_SEGMENTS, endpoint=False)  # (n,)
    ring = np.column_stack([c.x + c.radius * np.cos(angle), c.y + c.radius * np.sin(angle)])  # (n, 2)
    nxt = np.roll(ring, -1, axis=0)  # (n, 2)

    def lo(p: np.ndarray) -> np.ndarray:
        return np.column_stack([p, np.full(len(p), c.z0)])  # (n, 3)

    def hi(p: np.ndarray) -> np.ndarray:
        return np.column_stack([p, np.full(len(p), c.z1)])  # (n, 3)

    bottom_centre = np.tile([c.x, c.y, c.z0], (len(ring), 1))  # (n, 3)
    top_centre = np.tile([c.x, c.y, c.z1], (len(ring), 1))  # (n, 3)
    side_a = np.stack([lo(ring), lo(nxt), hi(nxt)], axis=1)  # (n, 3, 3)
    side_b = np.stack([lo(ring), hi(nxt), hi(ring)], axis=1)  # (n, 3, 3)
    top = np.stack([top_centre, hi(ring), hi(nxt)], axis=1)  # (n, 3, 3)
    bottom = np.stack([bottom_centre, lo(nxt), lo(ring)], axis=1)  # (n, 3, 3)
    return np.concatenate([side_a, side_b, top, bottom])


def _split_quads(quads: np.ndarray) -> np.ndarray:
    """(Q, 4, 3) quads -> (2Q, 3, 3) triangles with the same winding."""
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def _solid_triangles(shape: Box | Cylinder | Slab) -> tuple[np.ndarray, np.ndarray]:
    """A solid's triangles (T, 3, 3), counter-clockwise seen from outside, and which of them are the
    curved side of a cylinder (T,) bool."""
    if isinstance(shape, Box):
        tris = _split_quads(_box_quads(shape))
    elif isinstance(shape, Slab):
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        tris = _split_quads(
            shape.corners()[np.array(faces)]
        )  # (12, 3, 3): a right-handed frame keeps the winding
    else:
        tris = _cylinder_triangles(shape)
        side = np.arange(len(tris)) < 2 * CYLINDER_SEGMENTS  # (T,) the side comes first
        return tris, side
    return tris, np.zeros(len(tris), dtype=bool)


def surface_classes(tris: np.ndarray, curved: np.ndarray) -> np.ndarray:
    """Classes (T,) uint8 of triangles (T, 3, 3) as a Quake 3 map's faces get them (ingest.bsp): floor or
    ceiling where the normal's |z| >= HORIZONTAL_NZ (facing up or down), patch where `curved` (T,) bool,
    else wall."""
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])  # (T, 3)
    nz = normal[:, 2] / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)  # (T,)
    classes = np.full(len(tris), bsp.CLASS_WALL, dtype=np.uint8)  # (T,) uint8
    classes[nz >= bsp.HORIZONTAL_NZ] = bsp.CLASS_FLOOR
    classes[nz <= -bsp.HORIZONTAL_NZ] = bsp.CLASS_CEILING
    classes[curved] = bsp.CLASS_PATCH
    return classes


def mesh_layout(layout: Layout, semantics: Semantics | str = Semantics.OBJECT) -> Scene:
    """Triangulate a layout: air boundary (floor/wall/ceiling), solids, and the open-top barrier; face
    classes as `semantics` says (Semantics)."""
    quads, normal = _air_quads(air_grid(layout.air))  # (Q, 4, 3), (Q,)
    quad_class = np.full(len(quads), WALL, dtype=np.uint8)  # (Q,) uint8
    quad_class[normal == 3] = FLOOR
    quad_class[normal == -3] = CEILING
    lid = np.zeros(len(quads), dtype=bool)  # (Q,) bool
    if layout.void:
        lid = np.ones(len(quads), dtype=bool)
    elif layout.open_top is not None:
        lid = (normal == -3) & np.isclose(quads[:, 0, 2], layout.open_top)
    tris = [_split_quads(quads[~lid])]  # list of (T, 3, 3)
    classes = [np.tile(quad_class[~lid], 2)]  # list of (T,)
    curved = [np.zeros(len(tris[0]), dtype=bool)]  # list of (T,)
    for solid in layout.solids:
        shape_tris, side = _solid_triangles(solid.shape)
        tris.append(shape_tris)
        classes.append(np.full(len(shape_tris), solid.cls, dtype=np.uint8))
        curved.append(side)
    drawn = np.concatenate(tris)  # (F, 3, 3)
    face_class: np.ndarray = np.concatenate(classes)  # (F,) uint8
    class_names: tuple[str, ...] = CLASS_NAMES
    if Semantics(semantics) == Semantics.SURFACE:
        face_class, class_names = surface_classes(drawn, np.concatenate(curved)), bsp.CLASS_NAMES
    barrier = _split_quads(quads[lid])  # (Fb, 3, 3)
    corners = np.concatenate([drawn, barrier]).reshape(-1, 3)  # ((F + Fb)·3, 3)
    vertices, index = np.unique(np.round(corners, 6), axis=0, return_inverse=True)  # (V, 3), ((F + Fb)·3,)
    index = index.reshape(-1, 3).astype(np.int64)  # (F + Fb, 3)
    return Scene(
        name=f"{layout.family.value}_{layout.seed}",
        vertices=vertices.astype(np.float64),
        faces=index[: len(drawn)],
        face_class=face_class,
        class_names=class_names,
        barrier_faces=index[len(drawn) :],
        seeds=layout.seeds.astype(np.float64),
    )


def generate_scene(family: Family | str, seed: int, semantics: Semantics | str = Semantics.OBJECT) -> Scene:
    """One procedural scene of a family, deterministic in (family, seed), its faces classed by `semantics`."""
    return mesh_layout(build_layout(family, seed), semantics)


# ---------------------------------------------------------------------------------------------
# Writing


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = [f"# navi procedural scene: {len(vertices)} vertices, {len(faces)} faces, meters, +Z up"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    path.write_text("\n".join(lines) + "\n", encoding="ascii")


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment navi procedural scene, meters, +Z up\n"
        f"element vertex {len(vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face_records = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])  # (F,) packed records
    face_records["n"] = 3
    face_records["v"] = faces
    with path.open("wb") as out:
        out.write(header.encode("ascii"))
        out.write(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
        out.write(face_records.tobytes())


def write_scene_mesh(scene: Scene, path: str | os.PathLike[str]) -> Path:
    """Write the drawn triangles as .obj or .ply plus the `<stem>.scene.json` sidecar (classes, seeds, barriers).

    `load_scene(path)` reads both back: same drawn triangles in the same order, same classes,
    seeds and barrier triangles. Returns the mesh path.
    """
    out = Path(path)
    suffix = out.suffix.lower()
    if suffix not in (".obj", ".ply"):
        raise ValueError(f"write_scene_mesh writes .obj or .ply, not {suffix or '(none)'!r}")
    used = np.unique(scene.faces)  # (U,)
    remap = np.full(len(scene.vertices), -1, dtype=np.int64)  # (V,)
    remap[used] = np.arange(len(used))
    vertices, faces = scene.vertices[used], remap[scene.faces]  # (U, 3), (F, 3)
    barrier_used = np.unique(scene.barrier_faces)  # (Ub,)
    barrier_remap = np.full(len(scene.vertices), -1, dtype=np.int64)  # (V,)
    barrier_remap[barrier_used] = np.arange(len(barrier_used))
    out.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".obj":
        _write_obj(out, vertices, faces)
    else:
        _write_ply(out, vertices, faces)
    write_sidecar(
        out,
        Sidecar(
            face_class=scene.face_class,
            class_names=scene.class_names,
            seeds=scene.seeds,
            barrier_vertices=scene.vertices[barrier_used],
            barrier_faces=barrier_remap[scene.barrier_faces],
        ),
    )
    return out


def parse_entry(entry: Family | str) -> tuple[Family, float]:
    """(family, largest scale) of a corpus entry `FAMILY` or `FAMILY@S` with S >= 1; ValueError otherwise
    (an unknown family names the known ones)."""
    name, _, scale = str(entry.value if isinstance(entry, Family) else entry).partition("@")
    if name not in {f.value for f in FAMILIES}:
        raise ValueError(f"unknown family {name!r}; known: {', '.join(f.value for f in FAMILIES)}")
    try:
        largest = float(scale) if scale else 1.0
    except ValueError:
        largest = 0.0
    if not 1.0 <= largest <= 100.0:
        raise ValueError(f"entry {entry!r}: the scale after @ must be a number from 1 to 100")
    return Family(name), largest


def generate_corpus(
    out_dir: str | os.PathLike[str],
    count: int,
    seed: int,
    families: Sequence[Family | str] | None = None,
    progress: Callable[[int, int, Path], None] | None = None,
    semantics: Semantics | str = Semantics.OBJECT,
) -> list[Path]:
    """Write `count` scenes into out_dir as `<family>_<index>.obj` (+ sidecars), cycling the families
    (DEFAULT_ENTRIES when None), their faces classed by `semantics`.

    Scene i uses entry families[i % len(families)] and a seed derived from (seed, i): the same
    arguments always write the same files. An entry is a family or `FAMILY@S` (parse_entry): its scenes
    are scaled about the origin, seeds too, by S ** u, u uniform in [0, 1] from (seed, i), so an atrium
    becomes a stadium and a field of platforms a valley: open space no unscaled family holds. Returns the
    mesh paths in order.
    """
    chosen = [parse_entry(f) for f in (families or DEFAULT_ENTRIES)]
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    root = Path(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    for i in range(count):
        family, scale_max = chosen[i % len(chosen)]
        scene_seed = int(np.random.SeedSequence([seed, i]).generate_state(1)[0])
        scene = generate_scene(family, scene_seed, semantics)
        if scale_max > 1.0:
            u = np.random.default_rng(np.random.SeedSequence([seed, i, SCALE_STREAM])).random()
            factor = float(scale_max**u)
            scene = replace(scene, vertices=scene.vertices * factor, seeds=scene.seeds * factor)
        path = write_scene_mesh(scene, root / f"{family.value}_{i:04d}.obj")
        paths.append(path)
        if progress is not None:
            progress(i + 1, count, path)
    return paths
