"""Detached parts: geometry that no seed can reach and that only widens the compile cube.

A Quake 3 map can hold scenery far outside its sealed level: the room a portal-sky camera looks at,
distant backdrops. Nothing in the level reaches them, but the cube the compiler fits round every
vertex grows to hold them, and at a fixed resolution every voxel grows with it (oa_dm3: a cube about
630 m wide and 1.2 m voxels at 512³, for a level under 90 m across).

The rule. Surfaces are grouped into parts: two triangles are in the same part when they share a
coarse cell (`cell_m` meters) or lie in neighbouring cells, or when one triangle spans both. The parts
whose box holds a seed are kept, less hulls whose box holds all the others, then every part whose box
meets the kept box without holding it (`kept_parts`). The rest are dropped. That is only a guess at the
level: the compiler fills from the seeds in the smaller cube and, if the fill reaches its border (the
kept parts do not close the level), compiles the whole scene instead (navi_compiler.compile). When
the fill stays inside, it holds all the space the seeds reach, so the dropped parts are unreachable.

Shapes: V vertices, F drawn faces, Fb barrier faces, S seeds, C occupied cells, E cell pairs, P parts.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from navi_compiler.scene import Scene

DETACHED_CELL_M = 8.0
"""Meters per cell of the grouping grid: surfaces closer than about this belong to one part."""

_NEIGHBOURS = np.array(
    [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)]
)  # (13, 3) int64: half of the 26 neighbour offsets (the other half are their pairs' reverses)


@dataclass(frozen=True)
class Detached:
    """What drop_detached removed: its parts, drawn and barrier triangles, and the box before/after."""

    parts: int
    faces: int
    barrier_faces: int
    bounds_before: tuple[np.ndarray, np.ndarray]  # ((3,), (3,)) meters
    bounds_after: tuple[np.ndarray, np.ndarray]  # ((3,), (3,)) meters


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of n nodes joined by the edges (a[e], b[e]): (n,) int64, each node's
    smallest member index. Min-label propagation with pointer jumping, vectorised over the edges."""
    label = np.arange(n, dtype=np.int64)  # (n,)
    while True:
        m = np.minimum(label[a], label[b])  # (E,)
        new = label.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]  # pointer jump: a node takes its label's label
        if np.array_equal(new, label):
            return label
        label = new


def part_of_triangles(
    vertices: np.ndarray, triangles: np.ndarray, cell_m: float = DETACHED_CELL_M
) -> np.ndarray:
    """(T,) int64: the part of each triangle (its vertices' (V, 3) rows, meters): the smallest index of
    an occupied cell of its part. Cells are occupied by vertices and centroids; a triangle joins the
    cells of its three vertices; neighbouring occupied cells (26-connected) join."""
    lo = vertices.min(axis=0)  # (3,)
    corners = vertices[triangles]  # (T, 3, 3)
    pts = np.concatenate([corners, corners.mean(axis=1, keepdims=True)], axis=1)  # (T, 4, 3)
    ijk = np.floor((pts - lo) / cell_m).astype(np.int64)  # (T, 4, 3)
    dims = ijk.reshape(-1, 3).max(axis=0) + 3  # (3,): room for the -1 / +1 neighbours after the shift
    key = ((ijk[..., 0] + 1) * dims[1] + ijk[..., 1] + 1) * dims[2] + ijk[..., 2] + 1  # (T, 4) int64
    cells, inverse = np.unique(key, return_inverse=True)  # (C,), (T * 4,)
    inverse = inverse.reshape(key.shape)  # (T, 4) cell index per point
    # edges: a triangle's points share its part; occupied neighbours share theirs
    tri_a = np.concatenate([inverse[:, 0], inverse[:, 0], inverse[:, 0]])  # (3T,)
    tri_b = np.concatenate([inverse[:, 1], inverse[:, 2], inverse[:, 3]])  # (3T,)
    pairs = np.unique(np.stack([tri_a, tri_b], axis=1)[tri_a != tri_b], axis=0)  # (E1, 2)
    offsets = (_NEIGHBOURS[:, 0] * dims[1] + _NEIGHBOURS[:, 1]) * dims[2] + _NEIGHBOURS[:, 2]  # (13,)
    near = cells[:, None] + offsets[None, :]  # (C, 13) neighbour keys
    found = np.searchsorted(cells, near)  # (C, 13)
    hit = cells[np.minimum(found, len(cells) - 1)] == near  # (C, 13) bool: that neighbour is occupied
    src = np.broadcast_to(np.arange(len(cells))[:, None], near.shape)[hit]  # (E2,)
    a = np.concatenate([pairs[:, 0], src])  # (E,)
    b = np.concatenate([pairs[:, 1], found[hit]])  # (E,)
    label = _components(len(cells), a, b)  # (C,)
    return label[inverse[:, 0]]  # (T,)


def _contains(lo: np.ndarray, hi: np.ndarray, inner_lo: np.ndarray, inner_hi: np.ndarray) -> np.ndarray:
    """(P,) bool: box p ((P, 3) lo / hi) holds the box [inner_lo, inner_hi] ((3,) each)."""
    return np.asarray(((lo <= inner_lo) & (hi >= inner_hi)).all(axis=1))


def kept_parts(boxes_lo: np.ndarray, boxes_hi: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """(P,) bool: the parts kept, given each part's box ((P, 3) each, meters) and the seeds (S, 3).
    1. The parts whose box holds a seed, less shells: while two or more are left, a part whose box
       holds the box of all the others (a hull round everything, such as one brush round the level
       and its backdrops) leaves. 2. Every part whose box meets the kept parts' box joins, unless its
       box holds that whole box (a shell again), to a fixed point. 3. If a seed lies outside the kept
       parts' box, or no box holds a seed, every part is kept."""
    keep_all = np.ones(len(boxes_lo), dtype=bool)
    if len(seeds) == 0:
        return keep_all
    holds = np.asarray(((seeds[None] >= boxes_lo[:, None]) & (seeds[None] <= boxes_hi[:, None])).all(axis=2))
    keep = np.asarray(holds.any(axis=1))  # (P,) bool; holds: (P, S) bool
    while keep.sum() >= 2:
        shells: np.ndarray = np.zeros_like(keep)  # (P,) bool
        for k in np.flatnonzero(keep):
            others = keep.copy()
            others[k] = False
            lo, hi = boxes_lo[others].min(axis=0), boxes_hi[others].max(axis=0)  # (3,), (3,)
            shells[k] = _contains(boxes_lo[k : k + 1], boxes_hi[k : k + 1], lo, hi)[0]
        if not shells.any() or shells[keep].all():
            break
        keep &= ~shells
    if not keep.any():
        return keep_all
    while True:
        lo, hi = boxes_lo[keep].min(axis=0), boxes_hi[keep].max(axis=0)  # (3,), (3,)
        meets = ((boxes_lo <= hi) & (boxes_hi >= lo)).all(axis=1)  # (P,)
        joins = meets & ~_contains(boxes_lo, boxes_hi, lo, hi) & ~keep  # (P,)
        if not joins.any():
            break
        keep |= joins
    if not ((seeds >= lo) & (seeds <= hi)).all():
        return keep_all
    return keep


def drop_detached(
    scene: Scene, seeds: np.ndarray | None = None, cell_m: float = DETACHED_CELL_M
) -> tuple[Scene, Detached | None]:
    """The scene without its detached parts (module docstring), and what was dropped (None: nothing).
    seeds: (S, 3) meters, the fill's seeds (default: the scene's own). Without seeds the scene is
    returned as it is."""
    seeds = scene.seeds if seeds is None else seeds
    if len(seeds) == 0 or cell_m <= 0:
        return scene, None
    triangles = np.concatenate([scene.faces, scene.barrier_faces])  # (F + Fb, 3)
    part = part_of_triangles(scene.vertices, triangles, cell_m)  # (F + Fb,)
    ids, which = np.unique(part, return_inverse=True)  # (P,), (F + Fb,)
    corners = scene.vertices[triangles]  # (F + Fb, 3, 3)
    boxes_lo = np.full((len(ids), 3), np.inf)  # (P, 3)
    boxes_hi = np.full((len(ids), 3), -np.inf)  # (P, 3)
    np.minimum.at(boxes_lo, which, corners.min(axis=1))
    np.maximum.at(boxes_hi, which, corners.max(axis=1))
    keep = kept_parts(boxes_lo, boxes_hi, seeds)  # (P,)
    if keep.all():
        return scene, None
    keep_tri = keep[which]  # (F + Fb,) bool
    n_faces = len(scene.faces)
    keep_faces, keep_barrier = keep_tri[:n_faces], keep_tri[n_faces:]  # (F,), (Fb,)
    if not keep_faces.any():
        return scene, None  # the seeds' parts hold no drawn surface: leave the scene to the fill's rules
    used = np.unique(
        np.concatenate([scene.faces[keep_faces].ravel(), scene.barrier_faces[keep_barrier].ravel()])
    )
    remap = np.full(len(scene.vertices), -1, dtype=np.int64)  # (V,)
    remap[used] = np.arange(len(used))
    out = replace(
        scene,
        vertices=scene.vertices[used],  # (U, 3)
        faces=remap[scene.faces[keep_faces]],  # (F', 3)
        face_class=scene.face_class[keep_faces],  # (F',)
        barrier_faces=remap[scene.barrier_faces[keep_barrier]],  # (Fb', 3)
    )
    dropped = Detached(
        parts=int((~keep).sum()),
        faces=int((~keep_faces).sum()),
        barrier_faces=int((~keep_barrier).sum()),
        bounds_before=scene.bounds,
        bounds_after=out.bounds,
    )
    return out, dropped
