"""Free space of a scene as a voxel grid, its connected parts and true path lengths through it.

A scene's free space at the drone's radius is sampled from its distance field on a lattice of `cell`
meters over the scene's bounds: voxel (i, j, k) has its centre at bounds_min + (i + 0.5, j + 0.5,
k + 0.5) * cell and is free when the distance there is at least the radius. Voxels connect to their 26
neighbours (faces, edges and corners, 1, sqrt 2 and sqrt 3 cells long) when both are free.

- `components` labels the connected parts (each by the smallest flat index in it; -1 where blocked) by
  repeated min-pooling over the 26-neighbourhood, as many passes as the longest part is wide.
- `geodesic` gives every free voxel's path length in meters to the nearest source voxel through free
  voxels (inf where no path), by repeated relaxation over the 26 neighbours: the exact shortest path on
  the voxel graph, what Dijkstra gives (`geodesic_ref`), up to float32 rounding. `geodesic_many` does
  the same for several single sources at once (one field each).

- `surface_distance` estimates every voxel's distance to the nearest surface. The distance field is
  exact only near surfaces (inside its bricks) and stores a lower bound farther away, so the samples
  alone would make open space look cramped. It takes the samples under one cell as sources and adds
  26-neighbour path lengths from them.

All are torch only, one pass over the grid per iteration, on the scene's device. `components_ref`,
`geodesic_ref` and `surface_distance_ref` are the plain-Python twins (breadth-first search, Dijkstra)
for small grids.
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
from navi_env.tracer.trace import sample_distance

OFFSETS: tuple[tuple[int, int, int], ...] = tuple(
    (i, j, k) for i, j, k in itertools.product((-1, 0, 1), repeat=3) if (i, j, k) != (0, 0, 0)
)
"""The 26 neighbours of a voxel, (di, dj, dk)."""
SAMPLE_CHUNK = 1 << 20
"""Points per distance-field call while sampling the lattice."""
MAX_VOXELS = 1 << 25
"""The largest lattice `free_space` builds (33.5M voxels; `lattice_cell` picks a coarser cell above it)."""


@dataclass(frozen=True)
class FreeSpace:
    """A scene's free space: `free` (X, Y, Z) bool and `clearance` (X, Y, Z) float32 meters on the
    lattice whose voxel (0, 0, 0) is centred at origin + cell / 2 (world meters)."""

    origin: tuple[float, float, float]
    cell: float
    radius: float
    free: torch.Tensor  # (X, Y, Z) bool
    clearance: torch.Tensor  # (X, Y, Z) float32

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
    """Sample scene `scene` of the corpus on a lattice of `cell` meters (see the module docstring); a
    lattice of more than MAX_VOXELS voxels is refused (see lattice_cell)."""
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
        index = torch.stack(
            (flat // (shape[1] * shape[2]), (flat // shape[2]) % shape[1], flat % shape[2]), 1
        )
        part = grid.centre_of(index).contiguous()  # (C, 3)
        ids = torch.full((part.shape[0],), scene, dtype=torch.int64, device=corpus.device)  # (C,)
        sample_distance(corpus, ids, part, out=clearance[start : start + part.shape[0]])
    clearance = clearance.reshape(shape)  # (X, Y, Z)
    return FreeSpace(lo, cell, radius, clearance >= radius, clearance)


def components(free: torch.Tensor) -> torch.Tensor:
    """Labels (X, Y, Z) int64 of the 26-connected parts of free (X, Y, Z) bool: the smallest flat index of
    the part, -1 where blocked."""
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


def settle(dist: torch.Tensor, cell: float, free: torch.Tensor | None = None) -> torch.Tensor:
    """Relax G fields (G, X, Y, Z) float32 over the 26 neighbours until no voxel changes: each voxel ends at
    the smallest start value plus 26-neighbour path length through `free` (X, Y, Z) bool voxels (inf
    outside them), or through every voxel where `free` is None."""
    x, y, z = dist.shape[1:]
    steps = [(o, cell * math.sqrt(sum(abs(c) for c in o))) for o in OFFSETS]  # offset, its length
    inf = torch.tensor(math.inf, device=dist.device)
    while True:
        padded = F.pad(dist[:, None], (1, 1, 1, 1, 1, 1), value=math.inf)[:, 0]  # (G, X+2, Y+2, Z+2)
        best = dist
        for (di, dj, dk), length in steps:
            near = padded[:, 1 + di : 1 + di + x, 1 + dj : 1 + dj + y, 1 + dk : 1 + dk + z]  # (G, X, Y, Z)
            best = torch.minimum(best, near + length)
        nxt = best if free is None else torch.where(free[None], best, inf)  # (G, X, Y, Z)
        if torch.equal(nxt, dist):
            return dist
        dist = nxt


def geodesic(free: torch.Tensor, sources: torch.Tensor, cell: float) -> torch.Tensor:
    """Path length (X, Y, Z) float32 meters from every voxel to the nearest of the source voxels
    (S, 3) int64 through 26-connected free voxels; inf where blocked or cut off. Sources must be free."""
    if sources.numel() and not bool(free[sources[:, 0], sources[:, 1], sources[:, 2]].all()):
        raise ValueError("every source voxel must be free")
    dist = torch.full(free.shape, math.inf, device=free.device)  # (X, Y, Z) float32
    dist[sources[:, 0], sources[:, 1], sources[:, 2]] = 0.0
    return settle(dist[None], cell, free)[0]


def geodesic_many(free: torch.Tensor, sources: torch.Tensor, cell: float) -> torch.Tensor:
    """`geodesic` from each of G single source voxels (G, 3) int64 at once: (G, X, Y, Z) float32, field g the
    path length to source g (one relaxation over the batch: as many passes as the longest path, not G
    times as many)."""
    if sources.numel() and not bool(free[sources[:, 0], sources[:, 1], sources[:, 2]].all()):
        raise ValueError("every source voxel must be free")
    g = sources.shape[0]
    dist = torch.full((g, *free.shape), math.inf, device=free.device)  # (G, X, Y, Z) float32
    dist[torch.arange(g, device=free.device), sources[:, 0], sources[:, 1], sources[:, 2]] = 0.0
    return settle(dist, cell, free)


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


def dijkstra_ref(start: torch.Tensor, cell: float, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Shortest 26-neighbour path lengths (X, Y, Z) float64 from every finite voxel of `start` (X, Y, Z),
    which starts at its value, through the voxels of `mask` (X, Y, Z) bool (all where None)."""
    shape = tuple(start.shape)
    dist = start.cpu().double().clone()
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
            if inside and (mask is None or mask[w]) and d + length < dist[w]:
                dist[w] = d + length
                heapq.heappush(heap, (d + length, w))
    return dist


def components_ref(free: torch.Tensor) -> torch.Tensor:
    """components by breadth-first search in Python (small grids)."""
    mask = free.cpu()
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
                if all(0 <= w[a] < shape[a] for a in range(3)) and mask[w] and label[w] < 0:
                    label[w] = 0
                    members.append(w)
                    todo.append(w)
        smallest = min((v[0] * shape[1] + v[1]) * shape[2] + v[2] for v in members)
        for v in members:
            label[v] = smallest
    return label


def geodesic_ref(free: torch.Tensor, sources: torch.Tensor, cell: float) -> torch.Tensor:
    """geodesic by Dijkstra in Python, float64 sums (small grids)."""
    mask = free.cpu()
    start = torch.full(tuple(mask.shape), math.inf, dtype=torch.float64)
    for s in sources.cpu().tolist():
        start[s[0], s[1], s[2]] = 0.0
    return dijkstra_ref(start, cell, mask).float()


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
    (`surface_distance`) standing in for the view's shortest depth. Kinematic (no yaw, no acceleration):
    a ceiling for flights over this lattice."""
    free = space.free.cpu()
    shape = tuple(free.shape)
    sx, sy = shape[1] * shape[2], shape[2]
    clear = surface_distance(space.clearance, space.cell).cpu().reshape(-1).numpy()  # (V,) float32
    ok = free.reshape(-1).numpy()  # (V,) bool
    origin, cell = space.origin, space.cell

    def cell_of(v: int) -> tuple[int, int, int]:
        """The world cell of `cell_m` meters holding voxel v's centre."""
        i, j, k = v // sx, (v // sy) % shape[1], v % sy
        return (
            math.floor((origin[0] + (i + 0.5) * cell) / cell_m),
            math.floor((origin[1] + (j + 0.5) * cell) / cell_m),
            math.floor((origin[2] + (k + 0.5) * cell) / cell_m),
        )

    moves = []  # (offset, flat step, seconds at full speed, meters) per neighbour
    for o in OFFSETS:
        length = space.cell * math.sqrt(sum(abs(c) for c in o))
        full = max(length / max_speed, space.cell * abs(o[2]) / max_vertical_speed)
        moves.append((o, o[0] * sx + o[1] * sy + o[2], full, length))
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
            for (di, dj, dk), step, full, length in moves:
                if not (0 <= i + di < shape[0] and 0 <= j + dj < shape[1] and 0 <= k + dk < shape[2]):
                    continue
                w = v + step
                if not ok[w]:
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
