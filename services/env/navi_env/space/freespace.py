"""Free space of a scene as a voxel grid, its connected parts and true path lengths through it.

A scene's free space at the drone's radius is sampled from its distance field on a lattice of `cell`
meters over the scene's bounds: voxel (i, j, k) has its centre at bounds_min + (i + 0.5, j + 0.5,
k + 0.5) * cell and is free when the distance there is at least the radius. Voxels connect to their 26
neighbours (faces, edges and corners, 1, sqrt 2 and sqrt 3 cells long) through passable edges.

The edges: a wall thinner than the cell (or its diagonal) can stand between two free voxel centres, so
free ends alone do not make an edge passable. `free_space` tests the straight segment between the
centres of every pair of free neighbours (`cast_edges`): it sphere-traces the scene from one centre
towards the other with the tracer (navi_env.tracer.trace) with the drone's radius as its hit threshold,
and the edge is passable when the ray reaches the far centre. A segment crosses a surface, and its edge
is cut, when the walk samples the distance field inside solid or within the radius of a surface on the
way. A ray steps by the sampled distance (at least the radius) and stops at the first sample below the
radius, so a passable segment keeps about half the radius from every surface all along (it never
enters solid) and a cut one came within the radius of one: a wall of any thickness cuts, and so does a
gap narrower than the drone. Edges are stored once per pair, for the 13 offsets of EDGE_OFFSETS (the
other 13 are their reverses): `FreeSpace.edges` (O=13, X, Y, Z) bool, edges[o, i, j, k] the edge from
voxel (i, j, k) to (i, j, k) + EDGE_OFFSETS[o], False where either end is blocked or outside the grid.
Every function below takes the edges (None: every pair of free neighbours connects, `open_edges`).

- `components` labels the connected parts (each by the smallest flat index in it; -1 where blocked):
  without edges by repeated min-pooling over the 26-neighbourhood, as many passes as the longest part
  is wide; with edges by taking the least label over the 26 neighbours through passable edges, then
  each voxel its label's label (pointer jumping: a label is the index of a voxel of the part), until
  nothing changes.
- `geodesic` gives every free voxel's path length in meters to the nearest source voxel through free
  voxels (inf where no path), by repeated relaxation over the 26 neighbours (through passable edges
  only, when given): the exact shortest path on the voxel graph, what Dijkstra gives (`geodesic_ref`),
  up to float32 rounding. `geodesic_many` does the same for several single sources at once (one field
  each).

With edges a pass adds to each shifted neighbour value the cost of the edge (`edge_costs`: its length,
or 0 for labels, inf when cut), so it costs what a pass without edges does, plus a (13, X+2, Y+2, Z+2)
float32 cost table held while it runs (52 bytes a voxel; the edges themselves are 13 bytes a voxel).
`cast_edges` casts rays only from voxels whose clearance is at most an edge's length: from the others
the edge lies inside the ball the distance field certifies free, and the tracer's first step would pass
its end.

- `surface_distance` estimates every voxel's distance to the nearest surface. The distance field is
  exact only near surfaces (inside its bricks) and stores a lower bound farther away, so the samples
  alone would make open space look cramped. It takes the samples under one cell as sources and adds
  26-neighbour path lengths from them (every neighbour, no edges: a distance, not a flight).

All are torch only, on the scene's device: one pass over the grid per iteration, except the relaxation
of path lengths and surface distances on a CPU (`settle`), which `settle_frontier` runs from the voxels
that changed (the same fields, bit for bit; on czest3ctf's 215 × 139 × 36 lattice, 16 goal fields in
4.2 s on 2 cores instead of 290 s). `components_ref`, `geodesic_ref` and `surface_distance_ref` are the
plain-Python twins (breadth-first search, Dijkstra) for small grids; `edge_clearance_ref` samples the
distance field densely along every edge (the slow twin of `cast_edges`).
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from navi_env.tracer.scene import SceneCorpus
from navi_env.tracer.trace import sample_distance, trace

OFFSETS: tuple[tuple[int, int, int], ...] = tuple(
    (i, j, k) for i, j, k in itertools.product((-1, 0, 1), repeat=3) if (i, j, k) != (0, 0, 0)
)
"""The 26 neighbours of a voxel, (di, dj, dk)."""
EDGE_OFFSETS: tuple[tuple[int, int, int], ...] = OFFSETS[13:]
"""The 13 offsets after (0, 0, 0) in lexicographic order, one per pair of opposite neighbours: the edge
from voxel v to v + EDGE_OFFSETS[o] is FreeSpace.edges[o] at v (OFFSETS[12 - o] is its reverse)."""
SAMPLE_CHUNK = 1 << 20
"""Points per distance-field call while sampling the lattice."""
MAX_VOXELS = 1 << 25
"""The largest lattice `free_space` builds (33.5M voxels; `lattice_cell` picks a coarser cell above it)."""
NEAR_MARGIN = 1e-3
"""`cast_edges` casts the edges of voxels whose clearance is at most their length times 1 + NEAR_MARGIN
(the rest pass at the tracer's first step; the margin covers the tracer's rounding to voxel units)."""


@dataclass(frozen=True)
class FreeSpace:
    """A scene's free space: `free` (X, Y, Z) bool and `clearance` (X, Y, Z) float32 meters on the
    lattice whose voxel (0, 0, 0) is centred at origin + cell / 2 (world meters), and its passable
    `edges` (O, X, Y, Z) bool (see the module docstring; None: every pair of free neighbours connects)."""

    origin: tuple[float, float, float]
    cell: float
    radius: float
    free: torch.Tensor  # (X, Y, Z) bool
    clearance: torch.Tensor  # (X, Y, Z) float32
    edges: torch.Tensor | None = None  # (O, X, Y, Z) bool, O = 13 EDGE_OFFSETS

    def centre_of(self, index: torch.Tensor) -> torch.Tensor:
        """World positions (M, 3) float32 of the voxel centres at indices (M, 3) int64."""
        origin = torch.tensor(self.origin, dtype=torch.float64, device=index.device)  # (3,)
        return (origin + (index.double() + 0.5) * self.cell).float()

    def voxel(self, points: torch.Tensor) -> torch.Tensor:
        """Voxel indices (M, 3) int64 holding world points (M, 3), clamped into the grid."""
        origin = torch.tensor(self.origin, dtype=torch.float64, device=points.device)  # (3,)
        shape = torch.tensor(self.free.shape, device=points.device)  # (3,) int64
        index = torch.floor((points.double() - origin) / self.cell).long()  # (M, 3)
        return torch.minimum(index.clamp(min=0), shape - 1)


def lattice_shape(corpus: SceneCorpus, scene: int, cell: float) -> tuple[int, int, int]:
    """Voxels per axis of scene `scene`'s lattice of `cell` meters over its bounds."""
    lo, hi = corpus.infos[scene].bounds_min, corpus.infos[scene].bounds_max
    x, y, z = (max(1, math.ceil((hi[a] - lo[a]) / cell)) for a in range(3))
    return x, y, z


def lattice_cell(corpus: SceneCorpus, scene: int, cell: float, max_voxels: int = MAX_VOXELS) -> float:
    """`cell`, or the smallest multiple of it by 1.5^k whose lattice of the scene has at most max_voxels
    voxels (a map whose bounds span hundreds of meters)."""
    while math.prod(lattice_shape(corpus, scene, cell)) > max_voxels:
        cell *= 1.5
    return cell


def free_space(corpus: SceneCorpus, scene: int, cell: float = 0.5, radius: float = 0.3) -> FreeSpace:
    """Sample scene `scene` of the corpus on a lattice of `cell` meters and test its edges (see the module
    docstring); a lattice of more than MAX_VOXELS voxels is refused (see lattice_cell)."""
    if cell <= 0.0 or radius < 0.0:
        raise ValueError(f"cell must be positive and radius non-negative, got {cell}, {radius}")
    lo = corpus.infos[scene].bounds_min
    shape = lattice_shape(corpus, scene, cell)
    if math.prod(shape) > MAX_VOXELS:
        raise ValueError(
            f"scene {corpus.infos[scene].name!r} at {cell} m is a lattice of {math.prod(shape):,} voxels, more "
            f"than {MAX_VOXELS:,}: use a coarser cell (lattice_cell gives one)"
        )
    grid = FreeSpace(lo, cell, radius, torch.zeros(0, dtype=torch.bool), torch.empty(0))
    total = shape[0] * shape[1] * shape[2]
    clearance = torch.empty(total, dtype=torch.float32, device=corpus.device)  # (V,)
    for start in range(0, total, SAMPLE_CHUNK):
        flat = torch.arange(start, min(start + SAMPLE_CHUNK, total), device=corpus.device)  # (C,) int64
        part = grid.centre_of(unflatten(flat, shape)).contiguous()  # (C, 3)
        ids = torch.full((part.shape[0],), scene, dtype=torch.int64, device=corpus.device)  # (C,)
        sample_distance(corpus, ids, part, out=clearance[start : start + part.shape[0]])
    clearance = clearance.reshape(shape)  # (X, Y, Z)
    space = FreeSpace(lo, cell, radius, clearance >= radius, clearance)
    return FreeSpace(lo, cell, radius, space.free, clearance, cast_edges(corpus, scene, space))


def unflatten(flat: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """Voxel indices (N, 3) int64 of flat indices (N,) int64 into a lattice of `shape` (X, Y, Z)."""
    return torch.stack((flat // (shape[1] * shape[2]), (flat // shape[2]) % shape[1], flat % shape[2]), 1)


def regions(
    offset: tuple[int, int, int], shape: tuple[int, ...]
) -> tuple[tuple[slice, slice, slice], tuple[slice, slice, slice]]:
    """The slices (a, b) of a lattice of `shape` (X, Y, Z) such that voxel v of a[...] has its neighbour
    v + offset at the same place of b[...]: every voxel whose neighbour lies inside the grid, and those
    neighbours."""
    a = tuple(slice(max(0, -d), n - max(0, d)) for d, n in zip(offset, shape, strict=True))
    b = tuple(slice(max(0, d), n - max(0, -d)) for d, n in zip(offset, shape, strict=True))
    return (a[0], a[1], a[2]), (b[0], b[1], b[2])


def open_edges(free: torch.Tensor) -> torch.Tensor:
    """Edges (O, X, Y, Z) bool between free neighbours of free (X, Y, Z) bool, every one passable: the
    lattice without the edge test (what edges=None means everywhere)."""
    shape = (len(EDGE_OFFSETS), *free.shape)
    edges = torch.zeros(shape, dtype=torch.bool, device=free.device)  # (O, X, Y, Z)
    for o, offset in enumerate(EDGE_OFFSETS):
        a, b = regions(offset, tuple(free.shape))
        edges[o][a] = free[a] & free[b]
    return edges


def cast_edges(corpus: SceneCorpus, scene: int, space: FreeSpace) -> torch.Tensor:
    """The passable edges (O, X, Y, Z) bool of `space`, scene `scene`'s free space (module docstring): of
    every edge between free neighbours, one ray of the tracer from the voxel centre towards its
    neighbour's, with the radius as the hit threshold (a floor of cell / 64 at radius 0) and the edge's
    length as the horizon; the edge is passable when the ray misses. Rays of a length go together, each
    free voxel casting its edges of that length in one launch, SAMPLE_CHUNK voxels at a time; a voxel
    whose clearance exceeds the length (NEAR_MARGIN) casts none, its edges being passable."""
    free = space.free
    shape = tuple(free.shape)
    edges = open_edges(free)  # (O, X, Y, Z) bool, narrowed below
    flat_edges = edges.view(len(EDGE_OFFSETS), -1)  # (O, V) bool, a view of edges
    hit_epsilon = max(space.radius, space.cell / 64)
    for steps in (1, 2, 3):  # face, edge and corner neighbours: 1, sqrt 2 and sqrt 3 cells
        group = [o for o, offset in enumerate(EDGE_OFFSETS) if sum(abs(c) for c in offset) == steps]
        horizon = space.cell * math.sqrt(steps)
        directions = torch.tensor(
            [EDGE_OFFSETS[o] for o in group], dtype=torch.float32, device=free.device
        ) / math.sqrt(steps)  # (R, 3) unit vectors
        # a voxel whose clearance exceeds the edge's length reaches its neighbours at the tracer's first
        # step (which moves the ray by that clearance): only the others cast
        near = space.clearance.reshape(-1) <= horizon * (1.0 + NEAR_MARGIN)  # (V,) bool
        casting = (free.reshape(-1) & near).nonzero()[:, 0]  # (F,) int64 voxels that cast here
        for start in range(0, casting.shape[0], SAMPLE_CHUNK):
            flat = casting[start : start + SAMPLE_CHUNK]  # (C,) int64
            origins = space.centre_of(unflatten(flat, shape)).contiguous()  # (C, 3)
            ids = torch.full((flat.shape[0],), scene, dtype=torch.int64, device=free.device)  # (C,)
            depth = torch.empty(flat.shape[0], len(group), device=free.device)  # (C, R) float32
            semantic = torch.empty(flat.shape[0], len(group), dtype=torch.uint8, device=free.device)  # (C, R)
            trace(
                corpus, ids, origins, directions, out_depth=depth, out_semantic=semantic,
                max_steps=math.ceil(horizon / hit_epsilon) + 4, horizon=horizon, hit_epsilon=hit_epsilon,
                skip_direction_validation=True,
            )  # fmt: skip
            clear = (semantic == 0) & (depth >= horizon)  # (C, R) bool: the far centre reached
            for r, o in enumerate(group):
                flat_edges[o, flat] &= clear[:, r]
    return edges


def components(free: torch.Tensor, edges: torch.Tensor | None = None) -> torch.Tensor:
    """Labels (X, Y, Z) int64 of the connected parts of free (X, Y, Z) bool through passable edges (O, X,
    Y, Z) bool (None: all 26 neighbours): the smallest flat index of the part, -1 where blocked."""
    if edges is not None:
        return _components_through(free, edges)
    blocked = float(free.numel())
    flat = torch.arange(free.numel(), device=free.device, dtype=torch.float64).reshape(free.shape)
    label = torch.where(free, flat, blocked)  # (X, Y, Z) float64: exact below 2^53
    while True:
        pooled = -F.max_pool3d(-label[None, None], 3, stride=1, padding=1)[
            0, 0
        ]  # (X, Y, Z) neighbourhood min
        nxt = torch.where(free, torch.minimum(label, pooled), blocked)  # (X, Y, Z)
        if torch.equal(nxt, label):
            return torch.where(free, label.long(), -1)
        label = nxt


def _components_through(free: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """`components` through passable edges: every label is the flat index of a voxel of its part, so
    after taking the least label across each passable edge a voxel may take its label's label."""
    blocked = float(free.numel())
    x, y, z = free.shape
    flat = torch.arange(free.numel(), device=free.device, dtype=torch.float64).reshape(free.shape)
    label = torch.where(free, flat, blocked)  # (X, Y, Z) float64: exact below 2^53
    costs = edge_costs(edges, [0.0] * len(EDGE_OFFSETS))  # 26 x (offset, (X, Y, Z) float32 0 or inf)
    end = torch.tensor([blocked], dtype=torch.float64, device=free.device)  # (1,) what blocked voxels read
    while True:
        padded = F.pad(label, (1, 1, 1, 1, 1, 1), value=blocked)  # (X+2, Y+2, Z+2)
        best = label
        for (di, dj, dk), cost in costs:
            near = padded[1 + di : 1 + di + x, 1 + dj : 1 + dj + y, 1 + dk : 1 + dk + z]  # (X, Y, Z)
            best = torch.minimum(best, near + cost)
        table = torch.cat((best.reshape(-1), end))  # (V + 1,) float64, blocked voxels' labels read V
        nxt = torch.minimum(best, table[best.long().reshape(-1)].reshape(best.shape))  # (X, Y, Z) jumped
        if torch.equal(nxt, label):
            return torch.where(free, label.long(), -1)
        label = nxt


def edge_costs(edges: torch.Tensor, values: list[float]) -> list[tuple[tuple[int, int, int], torch.Tensor]]:
    """Per neighbour offset d (all 26 of OFFSETS), what reaching voxel v from v + d costs: (X, Y, Z) float32
    views of one padded (O, X+2, Y+2, Z+2) tensor, values[o] through a passable edge of offset o (either
    way) and inf through a cut one or from outside the grid. The edge of v and v + d is stored at v when
    d is one of EDGE_OFFSETS and at v + d when it is a reverse."""
    x, y, z = edges.shape[1:]
    size = (len(EDGE_OFFSETS), x + 2, y + 2, z + 2)
    padded = torch.full(size, math.inf, device=edges.device)  # (O, X+2, Y+2, Z+2) float32
    for o, value in enumerate(values):  # one offset at a time: no second (O, X, Y, Z) float32 in memory
        padded[o, 1 : 1 + x, 1 : 1 + y, 1 : 1 + z] = torch.where(edges[o], value, math.inf)  # (X, Y, Z)
    costs = []
    for o, (di, dj, dk) in enumerate(EDGE_OFFSETS):
        costs.append(((di, dj, dk), padded[o, 1 : 1 + x, 1 : 1 + y, 1 : 1 + z]))  # (X, Y, Z) stored at v
        costs.append(
            ((-di, -dj, -dk), padded[o, 1 - di : 1 - di + x, 1 - dj : 1 - dj + y, 1 - dk : 1 - dk + z])
        )  # (X, Y, Z) stored at v - offset
    return costs


def neighbour_costs(
    cell: float, edges: torch.Tensor | None
) -> list[tuple[tuple[int, int, int], float | torch.Tensor]]:
    """Per neighbour offset d, the length of a step from v + d to v: a float (every pair connects) or, with
    `edges`, an (X, Y, Z) float32 view, inf where the edge is cut (edge_costs)."""
    if edges is None:
        return [(o, cell * math.sqrt(sum(abs(c) for c in o))) for o in OFFSETS]
    return list(edge_costs(edges, [cell * math.sqrt(sum(abs(c) for c in o)) for o in EDGE_OFFSETS]))


def settle(
    dist: torch.Tensor, cell: float, free: torch.Tensor | None = None, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """Relax G fields (G, X, Y, Z) float32 over the 26 neighbours until no voxel changes: each voxel ends at
    the smallest start value plus 26-neighbour path length through `free` (X, Y, Z) bool voxels (inf
    outside them), or through every voxel where `free` is None; with `edges` (O, X, Y, Z) bool a value
    passes between neighbours only through a passable edge. On a GPU by whole-grid passes
    (`settle_passes`); on a CPU by rounds over the voxels that changed (`settle_frontier`: the same fields
    bit for bit, 11-69 times faster there on czest3ctf's lattice)."""
    if dist.device.type == "cpu":
        return settle_frontier(dist, cell, free, edges)
    return settle_passes(dist, cell, free, edges)


def settle_passes(
    dist: torch.Tensor, cell: float, free: torch.Tensor | None = None, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """`settle` by whole-grid passes, each voxel taking the least neighbour value plus the step's length,
    until a pass changes nothing: as many passes as the longest path has steps."""
    x, y, z = dist.shape[1:]
    costs = neighbour_costs(cell, edges)  # offset, its length (inf where cut)
    inf = torch.tensor(math.inf, device=dist.device)
    while True:
        padded = F.pad(dist[:, None], (1, 1, 1, 1, 1, 1), value=math.inf)[:, 0]  # (G, X+2, Y+2, Z+2)
        best = dist
        for (di, dj, dk), cost in costs:
            near = padded[:, 1 + di : 1 + di + x, 1 + dj : 1 + dj + y, 1 + dk : 1 + dk + z]  # (G, X, Y, Z)
            best = torch.minimum(best, near + cost)
        nxt = best if free is None else torch.where(free[None], best, inf)  # (G, X, Y, Z)
        if torch.equal(nxt, dist):
            return dist
        dist = nxt


FRONTIER_CHUNK = 1 << 21
"""Frontier voxels relaxed at a time by `settle_frontier` (bounds its index tensors)."""


def settle_frontier(
    dist: torch.Tensor, cell: float, free: torch.Tensor | None = None, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """`settle` by rounds over a frontier: each round relaxes the neighbours of the voxels whose value fell
    in the round before (at first every finite start value). The work is the number of improvements times
    26 rather than every voxel times the number of passes, which is what a CPU pays for. It applies the
    same monotone update as `settle_passes`, in another order, from the same start, so it ends at the
    same fixed point, bit for bit. Returns a new (G, X, Y, Z) float32 tensor."""
    g, x, y, z = dist.shape
    yz, voxels = y * z, x * y * z
    costs = [(o, c if isinstance(c, float) else c.reshape(-1)) for o, c in neighbour_costs(cell, edges)]
    open_ = None if free is None else free.reshape(-1)  # (V,) bool
    value = dist.reshape(-1).clone()  # (G·V,) float32
    front = torch.isfinite(value).nonzero()[:, 0]  # (F,) int64 flat (g, voxel) indices
    first = True
    fell = torch.zeros_like(value, dtype=torch.bool)  # (G·V,) the voxels whose value fell this round
    while front.numel():
        fell.zero_()
        for chunk in front.split(FRONTIER_CHUNK):
            base = value[chunk]  # (C,) float32
            field, voxel = chunk // voxels, chunk % voxels  # (C,), (C,) int64
            i, j, k = voxel // yz, voxel // z % y, voxel % z  # (C,) int64 each
            for (di, dj, dk), cost in costs:  # the step from u = v + d to v
                ti, tj, tk = i - di, j - dj, k - dk  # (C,) int64 each
                inside = (ti >= 0) & (ti < x) & (tj >= 0) & (tj < y) & (tk >= 0) & (tk < z)  # (C,) bool
                near = (ti * yz + tj * z + tk).clamp(0, voxels - 1)  # (C,) int64 voxel v
                target = field * voxels + near  # (C,) int64 flat (g, v)
                step = cost if isinstance(cost, float) else cost[near]  # () or (C,) float32
                offer = base + step  # (C,) float32
                better = inside & (offer < value[target])  # (C,) bool
                if open_ is not None:
                    better &= open_[near]
                target = target[better]  # (B,)
                value.scatter_reduce_(0, target, offer[better], "amin")
                fell[target] = True
        if first and open_ is not None:  # as settle_passes' first pass: a start value in a blocked voxel
            value = torch.where(open_.repeat(g), value, math.inf)  # reached its neighbours, then reads inf
        first = False
        front = fell.nonzero()[:, 0]  # (F',) int64
    return value.view(g, x, y, z)


def geodesic(
    free: torch.Tensor, sources: torch.Tensor, cell: float, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """Path length (X, Y, Z) float32 meters from every voxel to the nearest of the source voxels
    (S, 3) int64 through free voxels and passable edges (O, X, Y, Z) bool (None: all 26 neighbours); inf
    where blocked or cut off. Sources must be free."""
    if sources.numel() and not bool(free[sources[:, 0], sources[:, 1], sources[:, 2]].all()):
        raise ValueError("every source voxel must be free")
    dist = torch.full(free.shape, math.inf, device=free.device)  # (X, Y, Z) float32
    dist[sources[:, 0], sources[:, 1], sources[:, 2]] = 0.0
    return settle(dist[None], cell, free, edges)[0]


def geodesic_many(
    free: torch.Tensor, sources: torch.Tensor, cell: float, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """`geodesic` from each of G single source voxels (G, 3) int64 at once: (G, X, Y, Z) float32, field g the
    path length to source g (one relaxation over the batch: as many passes as the longest path, not G
    times as many)."""
    if sources.numel() and not bool(free[sources[:, 0], sources[:, 1], sources[:, 2]].all()):
        raise ValueError("every source voxel must be free")
    g = sources.shape[0]
    dist = torch.full((g, *free.shape), math.inf, device=free.device)  # (G, X, Y, Z) float32
    dist[torch.arange(g, device=free.device), sources[:, 0], sources[:, 1], sources[:, 2]] = 0.0
    return settle(dist, cell, free, edges)


def surface_distance(sampled: torch.Tensor, cell: float, near: float | None = None) -> torch.Tensor:
    """Distance (X, Y, Z) float32 meters from every voxel centre to the nearest surface, from the lattice's
    distance samples (X, Y, Z) float32 of `cell` meters. The samples in [0, near) (default: one cell; exact
    there) are the sources. Every other voxel gets the shortest 26-neighbour path length to a source plus
    that source's sample, and never less than its own sample (a lower bound). The 26-neighbour metric is
    at most 12.8% longer than the straight line, so far from surfaces this can overestimate by that
    much. Solid voxels (sample < 0) and a lattice without sources keep their samples."""
    near = cell if near is None else near
    start = torch.where((sampled >= 0) & (sampled < near), sampled, math.inf)  # (X, Y, Z) float32
    dist = settle(start[None], cell)[0]  # (X, Y, Z)
    keep = (sampled < 0) | torch.isinf(dist)  # (X, Y, Z) bool
    return torch.where(keep, sampled, torch.maximum(sampled, dist))


def surface_distance_ref(sampled: torch.Tensor, cell: float, near: float | None = None) -> torch.Tensor:
    """surface_distance by multi-source Dijkstra in Python, float64 sums (small grids)."""
    near = cell if near is None else near
    values = sampled.cpu().double()
    start = torch.where((values >= 0) & (values < near), values, math.inf)  # (X, Y, Z) float64
    dist = dijkstra_ref(start, cell)
    keep = (values < 0) | torch.isinf(dist)
    return torch.where(keep, values, torch.maximum(values, dist)).float()


def passable_ref(edges: torch.Tensor | None, v: tuple[int, ...], o: tuple[int, int, int]) -> bool:
    """Whether edges (O, X, Y, Z) bool (None: all) let a path step from voxel v to its neighbour v + o (one
    of OFFSETS, inside the grid): the stored edge at v, or at v + o for the reverse offsets."""
    if edges is None:
        return True
    if o in EDGE_OFFSETS:
        return bool(edges[EDGE_OFFSETS.index(o), v[0], v[1], v[2]])
    back = EDGE_OFFSETS.index((-o[0], -o[1], -o[2]))
    return bool(edges[back, v[0] + o[0], v[1] + o[1], v[2] + o[2]])


def dijkstra_ref(
    start: torch.Tensor, cell: float, mask: torch.Tensor | None = None, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """Shortest 26-neighbour path lengths (X, Y, Z) float64 from every finite voxel of `start` (X, Y, Z),
    which starts at its value, through the voxels of `mask` (X, Y, Z) bool (all where None) and the
    passable edges (O, X, Y, Z) bool (all where None)."""
    shape = tuple(start.shape)
    dist = start.cpu().double().clone()
    links = None if edges is None else edges.cpu()
    heap: list[tuple[float, tuple[int, int, int]]] = [
        (float(dist[i, j, k]), (i, j, k)) for i, j, k in torch.isfinite(dist).nonzero().tolist()
    ]
    heapq.heapify(heap)
    lengths = [(o, cell * math.sqrt(sum(abs(c) for c in o))) for o in OFFSETS]
    while heap:
        d, v = heapq.heappop(heap)
        if d > dist[v]:
            continue
        for o, length in lengths:
            w = (v[0] + o[0], v[1] + o[1], v[2] + o[2])
            inside = all(0 <= w[a] < shape[a] for a in range(3))
            if inside and (mask is None or mask[w]) and passable_ref(links, v, o) and d + length < dist[w]:
                dist[w] = d + length
                heapq.heappush(heap, (d + length, w))
    return dist


def components_ref(free: torch.Tensor, edges: torch.Tensor | None = None) -> torch.Tensor:
    """components by breadth-first search in Python (small grids)."""
    mask = free.cpu()
    links = None if edges is None else edges.cpu()
    shape = tuple(mask.shape)
    label = torch.full(shape, -1, dtype=torch.int64)
    for start in itertools.product(*(range(n) for n in shape)):
        if not mask[start] or label[start] >= 0:
            continue
        members = [start]
        label[start] = 0
        todo = deque([start])
        while todo:
            v = todo.popleft()
            for o in OFFSETS:
                w = (v[0] + o[0], v[1] + o[1], v[2] + o[2])
                if (
                    all(0 <= w[a] < shape[a] for a in range(3))
                    and mask[w]
                    and label[w] < 0
                    and passable_ref(links, v, o)
                ):
                    label[w] = 0
                    members.append(w)
                    todo.append(w)
        smallest = min((v[0] * shape[1] + v[1]) * shape[2] + v[2] for v in members)
        for v in members:
            label[v] = smallest
    return label


def geodesic_ref(
    free: torch.Tensor, sources: torch.Tensor, cell: float, edges: torch.Tensor | None = None
) -> torch.Tensor:
    """geodesic by Dijkstra in Python, float64 sums (small grids)."""
    mask = free.cpu()
    start = torch.full(tuple(mask.shape), math.inf, dtype=torch.float64)
    for s in sources.cpu().tolist():
        start[s[0], s[1], s[2]] = 0.0
    return dijkstra_ref(start, cell, mask, edges).float()


def edge_clearance_ref(corpus: SceneCorpus, scene: int, space: FreeSpace, samples: int = 64) -> torch.Tensor:
    """The least distance-field sample (O, X, Y, Z) float32 meters along every edge of `space` (scene
    `scene`'s free space) between free neighbours, at samples + 1 evenly spaced points from the voxel's
    centre to its neighbour's (inf where either end is blocked or outside the grid): what `cast_edges`
    decides from, sampled densely (small grids)."""
    open_ = open_edges(space.free).cpu()  # (O, X, Y, Z) bool
    least = torch.full(open_.shape, math.inf)  # (O, X, Y, Z) float32
    for o, offset in enumerate(EDGE_OFFSETS):
        index = open_[o].nonzero()  # (E, 3) int64 voxels with an open edge at this offset
        if index.shape[0] == 0:
            continue
        start = space.centre_of(index).double()  # (E, 3)
        step = torch.tensor(offset, dtype=torch.float64) * space.cell  # (3,)
        along = torch.linspace(0.0, 1.0, samples + 1, dtype=torch.float64)  # (S,)
        points = (start[:, None, :] + along[None, :, None] * step).float().reshape(-1, 3)  # (E * S, 3)
        ids = torch.full((points.shape[0],), scene, dtype=torch.int64)  # (E * S,)
        dist = sample_distance(corpus, ids.to(corpus.device), points.to(corpus.device)).cpu()  # (E * S,)
        least[o][tuple(index.T)] = dist.reshape(index.shape[0], -1).amin(dim=1)
    return least


def reachable_cells(space: FreeSpace, labels: torch.Tensor, point: torch.Tensor, cell_m: float = 1.0) -> int:
    """Distinct world cells of `cell_m` meters (floor(position / cell_m), the evaluation's coverage cells)
    holding a free voxel centre of the part that contains world point (3,)."""
    label = labels[tuple(space.voxel(point[None])[0].tolist())]  # () int64
    if int(label) < 0:
        return 0
    centres = space.centre_of((labels == label).nonzero())  # (V, 3) the part's voxel centres
    return int(torch.unique(torch.floor(centres / cell_m).long(), dim=0).shape[0])


def coverage_bound(reachable: int, episode_steps: int, step_m: float, cell_m: float = 1.0) -> float:
    """An upper bound on coverage per 1,000 steps (distinct cells of `cell_m` meters entered) for episodes
    of `episode_steps` steps of at most `step_m` meters: no more cells than the part holds (`reachable`),
    and no more than a path of that length can enter (it crosses at most sqrt 3 cell faces per cell
    length flown, plus the cell it starts in)."""
    path_cells = math.floor(episode_steps * step_m * math.sqrt(3.0) / cell_m) + 1
    return 1000.0 * min(reachable, path_cells) / episode_steps


@dataclass(frozen=True)
class Flight:
    """What `greedy_coverage` flew: distinct cells entered, the seconds and meters it took, and its moves
    in order: (seconds, clearance, new) per move, the clearance its end's distance to the nearest surface
    (the state after the move, which the rewards read), new whether it entered a cell not entered before."""

    cells: int
    seconds: float
    meters: float
    moves: list[tuple[float, float, bool]] = field(default_factory=list)


def greedy_coverage(
    space: FreeSpace,
    start: torch.Tensor,
    seconds: float,
    scale: Callable[[float], float],
    max_speed: float,
    max_vertical_speed: float,
    cell_m: float = 1.0,
) -> Flight:
    """A planner with the map: from the free voxel holding world point `start` (3,), fly voxel centre to
    voxel centre, each time to the voxel of a not yet entered world cell of `cell_m` meters that is
    quickest to reach (Dijkstra on flight time), for `seconds` of flight. A move between neighbours flies
    at most max_speed and its height at most max_vertical_speed (m/s), both times scale(c), c the smaller
    clearance of its two ends: the env's proximity limiter, with the distance to the nearest surface
    (`surface_distance`) standing in for the view's shortest depth. Moves only through the space's
    passable edges (every one between free neighbours when it has none). Kinematic (no yaw, no
    acceleration): a ceiling for flights over this lattice."""
    free = space.free.cpu()
    shape = tuple(free.shape)
    sx, sy = shape[1] * shape[2], shape[2]
    clear = surface_distance(space.clearance, space.cell).cpu().reshape(-1).numpy()  # (V,) float32
    ok = free.reshape(-1).numpy()  # (V,) bool
    edges = open_edges(free) if space.edges is None else space.edges.cpu()  # (O, X, Y, Z) bool
    passable = edges.reshape(len(EDGE_OFFSETS), -1).numpy()  # (O, V) bool
    origin, cell = space.origin, space.cell

    def cell_of(v: int) -> tuple[int, int, int]:
        """The world cell of `cell_m` meters holding voxel v's centre."""
        i, j, k = v // sx, (v // sy) % shape[1], v % sy
        return (
            math.floor((origin[0] + (i + 0.5) * cell) / cell_m),
            math.floor((origin[1] + (j + 0.5) * cell) / cell_m),
            math.floor((origin[2] + (k + 0.5) * cell) / cell_m),
        )

    moves = []  # (offset, flat step, seconds at full speed, meters, edge row, edge stored at the far end)
    for o in OFFSETS:
        length = space.cell * math.sqrt(sum(abs(c) for c in o))
        full = max(length / max_speed, space.cell * abs(o[2]) / max_vertical_speed)
        back = o not in EDGE_OFFSETS
        row = EDGE_OFFSETS.index((-o[0], -o[1], -o[2]) if back else o)
        moves.append((o, o[0] * sx + o[1] * sy + o[2], full, length, row, back))
    here = int(((space.voxel(start.reshape(1, 3).cpu())[0]) * torch.tensor([sx, sy, 1])).sum())
    if not ok[here]:
        return Flight(0, 0.0, 0.0, [])
    entered = {cell_of(here)}
    clock = meters = 0.0
    flown: list[tuple[float, float, bool]] = []  # (seconds, clearance, new cell) per move
    while clock < seconds:
        # Dijkstra on flight time from `here` to the nearest voxel of a cell not entered yet
        best = {here: (0.0, 0.0, -1)}  # voxel -> (seconds, meters, previous voxel)
        heap = [(0.0, here)]
        goal = -1
        while heap:
            t, v = heapq.heappop(heap)
            if t > best[v][0]:
                continue
            if cell_of(v) not in entered:
                goal = v
                break
            i, j, k = v // sx, (v // sy) % shape[1], v % sy
            for (di, dj, dk), step, full, length, row, back in moves:
                if not (0 <= i + di < shape[0] and 0 <= j + dj < shape[1] and 0 <= k + dk < shape[2]):
                    continue
                w = v + step
                if not ok[w] or not passable[row, w if back else v]:
                    continue
                dt = full / scale(float(min(clear[v], clear[w])))
                if w not in best or t + dt < best[w][0]:
                    best[w] = (t + dt, best[v][1] + length, v)
                    heapq.heappush(heap, (t + dt, w))
        if goal < 0:  # every cell of the part entered
            break
        path = [goal]
        while best[path[-1]][2] >= 0:
            path.append(best[path[-1]][2])
        for a, b in zip(
            path[-1:0:-1], path[-2::-1], strict=True
        ):  # the moves from here to the goal, in order
            dt = best[b][0] - best[a][0]
            if clock + dt > seconds:
                return Flight(len(entered), clock, meters, flown)
            clock += dt
            meters += best[b][1] - best[a][1]
            reached = cell_of(b)
            new = reached not in entered
            entered.add(reached)
            flown.append((dt, float(clear[b]), new))
        here = goal
    return Flight(len(entered), clock, meters, flown)
