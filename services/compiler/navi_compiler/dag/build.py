"""DAG stage: a signed lattice of distance samples -> a deduplicated sparse voxel octree (`Gmdag`).

This is the NumPy reference; csrc/dag.h is its C++ twin and produces the same bytes.

Rules (docs/COMPILER.md, docs/GMDAG.md):
- The lattice is (R+1)^3 float32 samples in voxels, indexed [x, y, z], positive in free space.
- A brick (8^3 cells, 9^3 corner samples) is *far* when every sample is >= band (far free) or every
  sample is <= -band (far solid). Its far-code payload is floor(16 * lower) (capped at 2^29) where `lower` is the
  caller's `far_lower` for that brick or, by default, max(min |sample| - sqrt(3)/2, 0): any point of a
  cell lies within sqrt(3)/2 voxel of a corner, so this is a lower bound of the distance for any
  1-Lipschitz field whose samples do not over-estimate it.
- Other bricks are quantised: q = trunc(d / quant_step) clamped to [-127, 127], then moved one step
  toward zero where |q * quant_step| > |d| (float32 rounding), so no decoded sample is farther from
  the surface than the input.
- An internal node whose 8 children are far codes with one tag becomes a far code carrying the
  smallest payload. Identical bricks (samples and class) and identical nodes at one depth are
  shared: MurmurHash3 groups candidates, byte equality decides.
- Numbering: nodes breadth-first (by depth; within a depth in order of first reference, scanning
  the previous depth's nodes in index order and their children 0..7), bricks in order of first
  reference in that same scan. So children always have larger indices than their parents.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from navi_compiler.dag.murmur import murmur3_32_rows
from navi_compiler.gmdag import (
    BRICK_CELLS,
    BRICK_SAMPLES,
    BRICK_SIDE,
    FAR_UNITS,
    PAYLOAD_MASK,
    TAG_BRICK,
    TAG_FAR_FREE,
    TAG_FAR_SOLID,
    TAG_NODE,
    Gmdag,
    quant_step_for,
    validate_gmdag,
)

HALF_DIAGONAL = np.float32(math.sqrt(3.0) / 2.0)  # farthest a cell point can be from its nearest corner


def _check_lattice(lattice: np.ndarray) -> int:
    if lattice.ndim != 3 or lattice.dtype != np.float32 or len(set(lattice.shape)) != 1:
        raise ValueError(f"lattice must be (R+1, R+1, R+1) float32, got {lattice.shape} {lattice.dtype}")
    r = lattice.shape[0] - 1
    if r < BRICK_CELLS or r & (r - 1):
        raise ValueError(f"lattice resolution {r} is not a power of two >= {BRICK_CELLS}")
    if not np.isfinite(lattice).all():
        raise ValueError("lattice holds non-finite samples")
    return r


def brick_reduce(lattice: np.ndarray, op: np.ufunc) -> np.ndarray:
    """op-reduce every brick's 9^3 window (stride 8): (nb, nb, nb) float32, separably per axis."""
    out = lattice
    for axis in range(3):
        n_bricks = (out.shape[axis] - 1) // BRICK_CELLS
        acc = None
        for offset in range(BRICK_SIDE):
            sl = [slice(None)] * 3
            sl[axis] = slice(offset, offset + BRICK_CELLS * n_bricks, BRICK_CELLS)
            part = out[tuple(sl)]
            acc = part.copy() if acc is None else op(acc, part)
        assert acc is not None
        out = acc
    return out


def quantise(samples: np.ndarray, quant_step: float) -> np.ndarray:
    """Samples in voxels (float32) -> int8 codes, never decoding farther from zero than the input."""
    step = np.float32(quant_step)
    q = np.clip(np.trunc(samples / step), -127, 127)  # float32
    over = np.abs(q * step) > np.abs(samples)  # decoded farther from the surface than the sample
    q = q - np.sign(q) * over  # float32
    return q.astype(np.int8)


def far_payload(lower: np.ndarray) -> np.ndarray:
    """Lower bounds in voxels (float32) -> far-code payloads floor(16 * max(lower, 0)) (uint32, <= 2^29)."""
    scaled = np.floor(np.maximum(lower, np.float32(0)) * np.float32(FAR_UNITS))  # float32
    return np.minimum(scaled, np.float32(1 << 29)).astype(np.uint32)  # capped at 2^29 (exact in float32)


def brick_samples(lattice: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """The 729 samples of the bricks at `coords` ((K, 3) brick coordinates): (K, 729) float32 in file
    order (sample (i, j, k) at i + 9*j + 81*k, i along x)."""
    windows = np.lib.stride_tricks.sliding_window_view(lattice, (BRICK_SIDE,) * 3)[
        ::BRICK_CELLS, ::BRICK_CELLS, ::BRICK_CELLS
    ]  # (nb, nb, nb, 9, 9, 9) view, [bx, by, bz, x, y, z]
    picked = windows[coords[:, 0], coords[:, 1], coords[:, 2]]  # (K, 9, 9, 9) [x, y, z]
    return np.ascontiguousarray(picked.transpose(0, 3, 2, 1)).reshape(len(coords), BRICK_SAMPLES)


def dedup_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Deduplicate the rows of a (K, n) uint8 array: MurmurHash3 groups candidates, bytes decide.

    Returns (ids (K,) int64: each row's unique id in order of first appearance, first (U,) int64:
    the row index where each unique id first appears).
    """
    hashes = murmur3_32_rows(rows)  # (K,) uint32
    flat = rows.tobytes()
    width = rows.shape[1]
    groups: dict[int, list[int]] = {}  # hash -> unique ids with that hash
    firsts: list[int] = []  # unique id -> row index
    ids = np.empty(len(rows), np.int64)  # (K,)
    for i, h in enumerate(hashes.tolist()):
        key = flat[i * width : (i + 1) * width]
        candidates = groups.setdefault(h, [])
        for uid in candidates:
            j = firsts[uid]
            if flat[j * width : (j + 1) * width] == key:
                ids[i] = uid
                break
        else:
            ids[i] = len(firsts)
            candidates.append(len(firsts))
            firsts.append(i)
    return ids, np.array(firsts, np.int64)


def _children(words: np.ndarray) -> np.ndarray:
    """Child words of the next depth ((2n, 2n, 2n) [x, y, z]) -> (n, n, n, 8) per parent, c = x|y<<1|z<<2."""
    n = words.shape[0] // 2
    parts = [words[(c & 1) :: 2, ((c >> 1) & 1) :: 2, ((c >> 2) & 1) :: 2] for c in range(8)]
    assert all(p.shape == (n, n, n) for p in parts)
    return np.stack(parts, axis=-1)


def _first_appearance(ids: np.ndarray) -> np.ndarray:
    """Distinct values of `ids` in order of first appearance."""
    values, first = np.unique(ids, return_index=True)  # (U,), (U,)
    return values[np.argsort(first, kind="stable")]


def _merge_far(children: np.ndarray) -> np.ndarray:
    """(M, 8) uint32 child words -> (M,) uint32: the merged far word, or 0 where the node stays."""
    tags = children >> np.uint32(30)  # (M, 8)
    same_far = (tags >= TAG_FAR_FREE).all(axis=1) & (tags == tags[:, :1]).all(axis=1)  # (M,)
    payload = (children & np.uint32(PAYLOAD_MASK)).min(axis=1)  # (M,)
    return np.where(same_far, (tags[:, 0] << np.uint32(30)) | payload, np.uint32(0)).astype(np.uint32)


def _renumber(root: int, levels: int, level_nodes: list[np.ndarray]) -> tuple[int, np.ndarray, np.ndarray]:
    """Provisional ids -> canonical breadth-first numbering. `level_nodes[d]` holds depth d's distinct
    nodes ((P_d, 8) uint32, children referencing provisional ids of depth d+1); returns (root word,
    nodes (N, 8) uint32, brick order (Bn,) int64: provisional brick id of each final brick)."""
    if root >> 30 != TAG_NODE:
        if root >> 30 == TAG_BRICK:
            return TAG_BRICK << 30, np.zeros((0, 8), np.uint32), np.array([root & PAYLOAD_MASK], np.int64)
        return root, np.zeros((0, 8), np.uint32), np.zeros(0, np.int64)
    order = np.array([root & PAYLOAD_MASK], np.int64)  # (K_d,) provisional ids at depth d, final order
    out: list[np.ndarray] = []
    base = 0
    brick_order = np.zeros(0, np.int64)  # (Bn,) provisional brick ids, final order
    for d in range(levels):
        words = level_nodes[d][order].astype(np.int64)  # (K_d, 8)
        tags = words >> 30
        child_tag = TAG_NODE if d + 1 < levels else TAG_BRICK
        refs = tags == child_tag  # (K_d, 8)
        next_order = _first_appearance(words[refs] & PAYLOAD_MASK)  # (K_{d+1},)
        rank = np.zeros(
            int(next_order.max()) + 1 if len(next_order) else 0, np.int64
        )  # (P,) provisional -> final
        rank[next_order] = np.arange(len(next_order))
        child_base = base + len(order) if child_tag == TAG_NODE else 0
        words[refs] = (child_tag << 30) | (rank[words[refs] & PAYLOAD_MASK] + child_base)
        out.append(words.astype(np.uint32))
        base += len(order)
        if child_tag == TAG_NODE:
            order = next_order
        else:
            brick_order = next_order
    return TAG_NODE << 30, np.concatenate(out), brick_order


def _xyz(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def f32_inside(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """float64 coordinates inside [lo, hi] -> float32, nudged one ulp inward where rounding left the box."""
    out = values.astype(np.float32)  # (..., 3) float32
    below = out.astype(np.float64) < lo
    above = out.astype(np.float64) > hi
    out = np.where(below, np.nextafter(out, np.float32(np.inf)), out)  # (..., 3) float32
    return np.where(above, np.nextafter(out, np.float32(-np.inf)), out).astype(np.float32)


@dataclass(frozen=True)
class DagArrays:
    """The octree part of a Gmdag (what the DAG stage computes, in either engine)."""

    root: int  # child word of the root
    levels: int  # L = log2(R / 8)
    nodes: np.ndarray  # (N, 8) uint32 child words
    bricks: np.ndarray  # (Bn, 729) int8 quantised samples
    brick_class: np.ndarray  # (Bn,) uint8


def build_dag(
    lattice: np.ndarray,
    band: float = 4.0,
    brick_class: np.ndarray | None = None,
    far_lower: np.ndarray | None = None,
) -> DagArrays:
    """The DAG stage (see the module docstring); arguments as in `build_gmdag`."""
    r = _check_lattice(lattice)
    nb = r // BRICK_CELLS
    levels = int(math.log2(nb))
    band32 = np.float32(band)
    quant_step = quant_step_for(float(band32))
    classes = np.zeros((nb, nb, nb), np.uint8) if brick_class is None else brick_class  # (nb, nb, nb) uint8
    if classes.shape != (nb, nb, nb) or classes.dtype != np.uint8:
        raise ValueError(f"brick_class must be ({nb}, {nb}, {nb}) uint8, got {classes.shape} {classes.dtype}")

    bmin = brick_reduce(lattice, np.minimum)  # (nb, nb, nb) float32
    bmax = brick_reduce(lattice, np.maximum)  # (nb, nb, nb) float32
    far_free = bmin >= band32  # (nb, nb, nb) bool
    far_solid = bmax <= -band32  # (nb, nb, nb) bool
    if far_lower is None:
        lower = np.where(far_free, bmin, -bmax) - HALF_DIAGONAL  # (nb, nb, nb) float32
    else:
        if (
            far_lower.shape != (nb, nb, nb)
            or far_lower.dtype != np.float32
            or not np.isfinite(far_lower).all()
        ):
            raise ValueError(f"far_lower must be ({nb}, {nb}, {nb}) finite float32")
        lower = far_lower
    payload = far_payload(lower)  # (nb, nb, nb) uint32
    words = np.where(
        far_free,
        (TAG_FAR_FREE << 30) | payload,
        (TAG_FAR_SOLID << 30) | payload,
    ).astype(np.uint32)  # (nb, nb, nb) uint32 child words at the brick depth

    near = ~(far_free | far_solid)  # (nb, nb, nb) bool
    coords = np.argwhere(near)  # (K, 3) brick coordinates, x-major scan order
    codes = quantise(brick_samples(lattice, coords), quant_step)  # (K, 729) int8
    keys = np.concatenate([codes.view(np.uint8), classes[near][:, None]], axis=1)  # (K, 730) uint8
    brick_ids, brick_first = dedup_rows(keys)  # (K,), (U,)
    words[near] = (TAG_BRICK << 30) | brick_ids.astype(np.uint32)

    level_nodes: list[np.ndarray] = [np.zeros((0, 8), np.uint32)] * levels  # per depth: (P_d, 8) uint32
    for d in range(levels - 1, -1, -1):
        n = 1 << d
        children = _children(words).reshape(n**3, 8)  # (n^3, 8) uint32
        merged = _merge_far(children)  # (n^3,) uint32, 0 where a node stays
        stays = merged == 0  # (n^3,)
        node_ids, node_first = dedup_rows(np.ascontiguousarray(children[stays]).view(np.uint8))  # (M,), (P,)
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


def make_gmdag(
    arrays: DagArrays,
    *,
    origin: Sequence[float],
    voxel_size: float,
    band: float = 4.0,
    spawns: np.ndarray | None = None,
    class_names: Sequence[str] = ("unknown",),
    bounds: tuple[Sequence[float], Sequence[float]] | None = None,
    flags: int = 0,
) -> Gmdag:
    """Wrap DAG arrays with the cube placement and metadata into a validated Gmdag (arguments as in
    `build_gmdag`; spawns and bounds are rounded to float32 inside the cube)."""
    r = BRICK_CELLS << arrays.levels
    band32 = float(np.float32(band))
    cube_lo = np.array(origin, np.float64)  # (3,)
    cube_hi = cube_lo + r * float(voxel_size)  # (3,)
    lo, hi = (
        (cube_lo, cube_hi)
        if bounds is None
        else (np.array(bounds[0], np.float64), np.array(bounds[1], np.float64))
    )
    pts = (
        np.zeros((0, 3), np.float64) if spawns is None else np.asarray(spawns, np.float64).reshape(-1, 3)
    )  # (S, 3)
    g = Gmdag(
        resolution=r,
        levels=arrays.levels,
        root=arrays.root,
        origin=_xyz(cube_lo),
        voxel_size=float(voxel_size),
        band=band32,
        quant_step=quant_step_for(band32),
        nodes=arrays.nodes,
        bricks=arrays.bricks,
        brick_class=arrays.brick_class,
        spawns=f32_inside(pts, cube_lo, cube_hi),
        class_names=tuple(class_names),
        bounds_min=_xyz(f32_inside(lo, cube_lo, cube_hi)),
        bounds_max=_xyz(f32_inside(hi, cube_lo, cube_hi)),
        flags=flags,
    )
    validate_gmdag(g)
    return g


def build_gmdag(
    lattice: np.ndarray,
    *,
    origin: Sequence[float],
    voxel_size: float,
    band: float = 4.0,
    brick_class: np.ndarray | None = None,
    far_lower: np.ndarray | None = None,
    spawns: np.ndarray | None = None,
    class_names: Sequence[str] = ("unknown",),
    bounds: tuple[Sequence[float], Sequence[float]] | None = None,
    flags: int = 0,
) -> Gmdag:
    """Compress a signed lattice into a validated Gmdag.

    lattice: (R+1, R+1, R+1) float32 signed distances in voxels, [x, y, z], R a power of two >= 8.
    origin, voxel_size: the cube's min corner and cell edge, meters.
    band: samples are kept (quantised) in bricks with a sample |d| < band; quant_step = band / 127.
    brick_class: (R/8, R/8, R/8) uint8 class id per brick position (default all 0, unknown).
    far_lower: (R/8, R/8, R/8) float32 lower bound (voxels) of |distance| over each brick's closed cube,
        used for far bricks; default max(min |sample| - sqrt(3)/2, 0) (see the module docstring).
    spawns: (S, 3) known-free points, meters, inside the cube. bounds: (min, max) of the source
        geometry, meters (default: the cube). flags: GMDAG flag bits.
    """
    arrays = build_dag(lattice, band, brick_class, far_lower)
    return make_gmdag(
        arrays,
        origin=origin,
        voxel_size=voxel_size,
        band=band,
        spawns=spawns,
        class_names=class_names,
        bounds=bounds,
        flags=flags,
    )
