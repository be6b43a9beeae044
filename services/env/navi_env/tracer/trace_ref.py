"""The reference tracer: the traversal of csrc/ (gmdag_trace.h and its headers) in plain PyTorch, by ray.

Slow and obviously correct: every sample descends from the root through the file's child words (no
leaf grid, no leaf cache) and reads the file's 729 samples of a brick (decoded back from the corpus's
corner words), every operation is one float32 tensor op in the header's order, so it takes the same
steps as the compiled launchers and serves as their parity oracle. Same signature and semantics as
`navi_env.tracer.trace.trace`.

Shapes: B actors, R rays, M = B * R rays in flight, K rays being worked on, N query points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from navi_env.tracer.primitives import check_prims, prim_distance_ref, prim_hit_ref
from navi_env.tracer.scene import (
    W_BRICK_OFFSET,
    W_INV_VOXEL,
    W_LEVELS,
    W_NODE_OFFSET,
    W_ORIGIN,
    W_QUANT,
    W_RESOLUTION,
    W_ROOT,
    W_VOXEL,
    SceneCorpus,
)
from navi_env.tracer.trace import (
    DEFAULT_HIT_EPSILON_VOXELS,
    DEFAULT_HORIZON,
    DEFAULT_MAX_STEPS,
    validate_sample,
    validate_trace,
)

TAG_BRICK, TAG_FAR_FREE, TAG_FAR_SOLID = 1, 2, 3
PAYLOAD_MASK = 0x3FFFFFFF
FAR_UNIT = 1.0 / 16.0
REFINE_ITERATIONS = 6
SECANT_REACH = 16.0  # kSecantReach: a threshold stop reports the secant's zero at most this many d ahead
BIG = 3.0e38
F32 = torch.float32


@dataclass
class RefScene:
    """Per-ray copies of the scene records (all (M,) tensors) and the corpus buffers."""

    nodes: torch.Tensor  # (Nn * 8,) int64 child words as unsigned values
    bricks: torch.Tensor  # (Nb * 729,) float32 samples, file order (i + 9j + 81k)
    root: torch.Tensor  # (M,) int64
    node_offset: torch.Tensor  # (M,) int64
    brick_offset: torch.Tensor  # (M,) int64
    resolution: torch.Tensor  # (M,) int64
    levels: torch.Tensor  # (M,) int64
    origin: torch.Tensor  # (M, 3) float32
    voxel: torch.Tensor  # (M,) float32
    inv_voxel: torch.Tensor  # (M,) float32
    quant: torch.Tensor  # (M,) float32

    def take(self, idx: torch.Tensor) -> RefScene:
        """The records of rays idx (K,)."""
        return RefScene(
            self.nodes, self.bricks, self.root[idx], self.node_offset[idx], self.brick_offset[idx],
            self.resolution[idx], self.levels[idx], self.origin[idx], self.voxel[idx], self.inv_voxel[idx],
            self.quant[idx],
        )  # fmt: skip


def brick_samples(words: torch.Tensor) -> torch.Tensor:
    """(Nb * 729,) int8 samples in file order from corner words (Nb * 576,) int32 (layout in scene.py):
    sample (i, j, k) is byte 0 of word (i, j, k), or byte 1 of word (i - 1, j, k) when i = 8, byte 2
    of word (i, j - 1, k) when j = 8, byte 3 of word (7, 7, k) when both are 8; each byte is sample + 128."""
    w = words.view(-1, 8, 8, 9).long() & 0xFFFFFFFF  # (Nb, 8i, 8j, 9k) unsigned
    nb = w.shape[0]
    u = torch.zeros(nb, 9, 9, 9, dtype=torch.long, device=words.device)  # (Nb, 9i, 9j, 9k)
    u[:, :8, :8] = w & 0xFF
    u[:, 8, :8] = (w[:, 7] >> 8) & 0xFF
    u[:, :8, 8] = (w[:, :, 7] >> 16) & 0xFF
    u[:, 8, 8] = (w[:, 7, 7] >> 24) & 0xFF
    return (u - 128).to(torch.int8).permute(0, 3, 2, 1).reshape(-1)  # (Nb * 729,) in [k, j, i] order


def ref_scene(scenes: SceneCorpus, sid: torch.Tensor) -> RefScene:
    """Per-ray scene records for scene ids sid (M,) (already clamped into range)."""
    if scenes.atlas is not None:
        raise ValueError("the reference reads corner words: give it the corpus loaded on the CPU")
    rec = scenes.table[sid].long() & 0xFFFFFFFF  # (M, 16) int64 unsigned words
    frec = scenes.table[sid].view(F32)  # (M, 16) float32
    return RefScene(
        nodes=scenes.nodes.long() & 0xFFFFFFFF,
        bricks=brick_samples(scenes.bricks).to(F32),
        root=rec[:, W_ROOT],
        node_offset=rec[:, W_NODE_OFFSET],
        brick_offset=rec[:, W_BRICK_OFFSET],
        resolution=rec[:, W_RESOLUTION],
        levels=rec[:, W_LEVELS],
        origin=frec[:, W_ORIGIN : W_ORIGIN + 3],
        voxel=frec[:, W_VOXEL],
        inv_voxel=frec[:, W_INV_VOXEL],
        quant=frec[:, W_QUANT],
    )


@dataclass
class Field:
    """The field at K points (csrc/brick_sample.h FieldSample plus the leaf cube)."""

    dist: torch.Tensor  # (K,) float32 voxels
    solid: torch.Tensor  # (K,) bool
    far_free: torch.Tensor  # (K,) bool
    brick: torch.Tensor  # (K,) int64 corpus brick index or -1
    corner: torch.Tensor  # (K, 3) int64 leaf cube min corner
    shift: torch.Tensor  # (K,) int64 log2 leaf cube edge


def cell_of(x: torch.Tensor, resolution: torch.Tensor) -> torch.Tensor:
    """(K,) int64 cell index: floor, clamped to [0, R - 1] in float32 first."""
    hi = (resolution - 1).to(F32)  # (K,)
    return torch.minimum(torch.maximum(torch.floor(x), torch.zeros_like(x)), hi).long()


def descend(s: RefScene, cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Leaf word and log2 cube edge for cells (K, 3) int64: ((K,) int64, (K,) int64)."""
    word = s.root.clone()  # (K,)
    shift = s.levels + 3  # (K,)
    depth_max = int(s.levels.max()) if len(word) else 0
    for depth in range(depth_max):
        inner = (s.levels > depth) & ((word >> 30) == 0)  # (K,)
        shift = torch.where(inner, shift - 1, shift)
        child = (
            ((cells[:, 0] >> shift) & 1)
            | (((cells[:, 1] >> shift) & 1) << 1)
            | (((cells[:, 2] >> shift) & 1) << 2)
        )
        node = s.node_offset + (word & PAYLOAD_MASK)  # (K,)
        index = torch.where(inner, node * 8 + child, torch.zeros_like(node))  # (K,)
        fetched = s.nodes[index] if len(s.nodes) else torch.zeros_like(word)  # (K,)
        word = torch.where(inner, fetched, word)
    return word, shift


def brick_distance(s: RefScene, brick: torch.Tensor, local: torch.Tensor, frac: torch.Tensor) -> torch.Tensor:
    """Trilinear distance (K,) float32 voxels in bricks (K,) at cells local (K, 3) int64 in [0, 7]^3 of
    the brick with fractions frac (K, 3) float32 in [0, 1]."""
    base = brick.clamp(min=0) * 729 + local[:, 0] + 9 * local[:, 1] + 81 * local[:, 2]  # (K,)

    def c(off: int) -> torch.Tensor:
        return s.bricks[base + off] if len(s.bricks) else torch.zeros_like(frac[:, 0])  # (K,)

    fx, fy, fz = frac[:, 0], frac[:, 1], frac[:, 2]
    c000, c100, c010, c110 = c(0), c(1), c(9), c(10)
    c001, c101, c011, c111 = c(81), c(82), c(90), c(91)
    x00 = c000 + fx * (c100 - c000)
    x10 = c010 + fx * (c110 - c010)
    x01 = c001 + fx * (c101 - c001)
    x11 = c011 + fx * (c111 - c011)
    y0 = x00 + fy * (x10 - x00)
    y1 = x01 + fy * (x11 - x01)
    return (y0 + fz * (y1 - y0)) * s.quant


def field_at(s: RefScene, p: torch.Tensor, cells: torch.Tensor) -> Field:
    """The field at voxel-space points p (K, 3) whose cells (K, 3) are given."""
    word, shift = descend(s, cells)
    corner = (cells >> shift[:, None]) << shift[:, None]  # (K, 3)
    tag = word >> 30  # (K,)
    payload = word & PAYLOAD_MASK  # (K,)
    is_brick = tag == TAG_BRICK
    brick = torch.where(is_brick, s.brick_offset + payload, torch.full_like(payload, -1))  # (K,)
    far = payload.to(F32) * FAR_UNIT  # (K,)
    dist = torch.where(
        tag == TAG_FAR_SOLID, -far, torch.where(tag == TAG_FAR_FREE, far, torch.zeros_like(far))
    )
    if bool(is_brick.any()):
        frac = torch.clamp(p - cells.to(F32), 0.0, 1.0)  # (K, 3) position inside the cell
        inside = brick_distance(s, brick, (cells - corner).clamp(0, 7), frac)  # (K,)
        dist = torch.where(is_brick, inside, dist)
    return Field(dist, tag == TAG_FAR_SOLID, ~is_brick & (tag != TAG_FAR_SOLID), brick, corner, shift)


def cells_at(s: RefScene, p: torch.Tensor) -> torch.Tensor:
    """(K, 3) int64 cells of voxel-space points p (K, 3)."""
    return torch.stack([cell_of(p[:, k], s.resolution) for k in range(3)], dim=1)


def clip_slab(o: torch.Tensor, d: torch.Tensor, inv: torch.Tensor, res: torch.Tensor,
              t0: torch.Tensor, t1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """csrc/ray_walk.h clip_slab over (M,) rays."""
    ta = (0.0 - o) * inv
    tb = (res - o) * inv
    moving = d != 0
    t0 = torch.where(moving, torch.maximum(t0, torch.minimum(ta, tb)), t0)
    t1 = torch.where(moving, torch.minimum(t1, torch.maximum(ta, tb)), t1)
    outside = ~moving & ((o < 0) | (o > res))
    return t0, torch.where(outside, torch.full_like(t1, -1.0), t1)


def exit_time(
    o: torch.Tensor, d: torch.Tensor, inv: torch.Tensor, c: torch.Tensor, edge: torch.Tensor
) -> torch.Tensor:
    """csrc/ray_walk.h exit_time over (K,) rays."""
    bound = torch.where(d > 0, c + edge, c).to(F32)
    return torch.where(d == 0, torch.full_like(o, BIG), (bound - o) * inv)


def trace_ref(
    scenes: SceneCorpus,
    scene_ids: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    *,
    out_depth: torch.Tensor,
    out_semantic: torch.Tensor | None = None,
    yaw: torch.Tensor | None = None,
    out_steps: torch.Tensor | None = None,
    ray_order: torch.Tensor | None = None,
    max_steps: int = DEFAULT_MAX_STEPS,
    horizon: float = DEFAULT_HORIZON,
    hit_epsilon: float | None = None,
    skip_direction_validation: bool = False,
    prims: torch.Tensor | None = None,
    prim_world: torch.Tensor | None = None,
    hit_slope: float = 0.0,
) -> None:
    """Reference twin of `navi_env.tracer.trace.trace` (same arguments, same results; ray_order only
    schedules the compiled launchers, so it is validated and otherwise unused here). Primitive hits
    come from `obstacles.prim_hit_ref` in float64 (the kernel's are float32: equal to a tolerance)."""
    p = validate_trace(
        scenes, scene_ids, origins, directions, out_depth, out_semantic, yaw, out_steps, ray_order,
        max_steps, horizon, hit_epsilon, skip_direction_validation, hit_slope,
    )  # fmt: skip
    check_prims(prims, prim_world, p.batch, scenes.device, "one per actor")
    b, r = p.batch, p.rays
    m = b * r
    dev = scenes.device
    actor = torch.arange(b, device=dev).repeat_interleave(r)  # (M,)
    sid_raw = scene_ids.long()[actor]  # (M,)
    sid_ok = (sid_raw >= 0) & (sid_raw < len(scenes))  # (M,)
    s = ref_scene(scenes, sid_raw.clamp(0, len(scenes) - 1))
    dirs = (directions.expand(b, r, 3) if p.shared else directions).reshape(m, 3)  # (M, 3)
    dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    if yaw is not None:
        c, sn = torch.cos(yaw)[actor], torch.sin(yaw)[actor]  # (M,), (M,)
        dx, dy = c * dx - sn * dy, sn * dx + c * dy
    d = torch.stack([dx, dy, dz], dim=1)  # (M, 3)
    o = (origins[actor] - s.origin) * s.inv_voxel[:, None]  # (M, 3) voxel space
    res = s.resolution.to(F32)  # (M,)
    horizon32 = torch.tensor(p.horizon, dtype=F32, device=dev)
    reach = torch.full((m,), p.horizon, dtype=F32, device=dev)  # (M,) meters: the walk's end
    prim_t = torch.full((m,), math.inf, dtype=torch.float64, device=dev)  # (M,) first primitive hit
    prim_sem = torch.zeros(m, dtype=torch.int64, device=dev)  # (M,)
    if prims is not None and prims.shape[1] > 0:
        world = prim_world if prim_world is not None else torch.arange(b, dtype=torch.int32, device=dev)
        hit_t, hit_sem = prim_hit_ref(prims, world, origins, d.view(b, r, 3))  # (B, R) each
        prim_t, prim_sem = hit_t.reshape(m).to(dev), hit_sem.reshape(m).to(dev)
        reach = torch.minimum(reach, prim_t.clamp(max=3.0e38).float())
    if p.hit_epsilon > 0:
        eps = torch.tensor(p.hit_epsilon, dtype=F32, device=dev) * s.inv_voxel  # (M,)
    else:
        eps = torch.full((m,), DEFAULT_HIT_EPSILON_VOXELS, dtype=F32, device=dev)  # (M,)
    slope = torch.tensor(p.hit_slope, dtype=F32, device=dev)  # () float32, as the kernel rounds it
    inv = torch.where(d != 0, 1.0 / d, torch.full_like(d, BIG))  # (M, 3)
    t0 = torch.zeros(m, dtype=F32, device=dev)  # (M,)
    t1 = reach * s.inv_voxel  # (M,)
    for k in range(3):
        t0, t1 = clip_slab(o[:, k], d[:, k], inv[:, k], res, t0, t1)
    finite = torch.isfinite(o).all(dim=1) & torch.isfinite(d).all(dim=1)  # (M,)

    depth = torch.full((m,), p.horizon, dtype=F32, device=dev)  # (M,) meters
    depth[~sid_ok] = float("nan")
    semantic = torch.zeros(m, dtype=torch.int64, device=dev)  # (M,)
    steps = torch.zeros(m, dtype=torch.int64, device=dev)  # (M,)
    active = sid_ok & finite & (t0 <= t1)  # (M,)
    t = t0.clone()  # (M,)
    prev_t = t0.clone()  # (M,)
    prev_d = torch.full((m,), -1.0, dtype=F32, device=dev)  # (M,) below any free sample: no stop at sample 0
    last_brick = torch.full((m,), -1, dtype=torch.int64, device=dev)  # (M,)
    classes = scenes.brick_class.long()  # (Nb,)

    def semantic_of(brick: torch.Tensor) -> torch.Tensor:
        return torch.where(brick >= 0, 1 + classes[brick.clamp(min=0)] if len(classes) else 1, 1)  # (K,)

    for step in range(p.max_steps):
        idx = active.nonzero().squeeze(1)  # (K,)
        if len(idx) == 0:
            break
        sk = s.take(idx)
        ok, dk, tk = o[idx], d[idx], t[idx]
        steps[idx] = step + 1
        pk = ok + tk[:, None] * dk  # (K, 3)
        f = field_at(sk, pk, cells_at(sk, pk))
        lb = torch.where(f.brick >= 0, f.brick, last_brick[idx])  # (K,)
        last_brick[idx] = lb

        inside = f.solid | (f.dist < 0)  # (K,)
        hit_t = tk.clone()  # (K,)
        refine = inside & (step > 0)
        if bool(refine.any()):
            ridx = refine.nonzero().squeeze(1)  # (J,)
            rs = sk.take(ridx)
            lo, hi = prev_t[idx][ridx], tk[ridx]  # (J,), (J,)
            flo, fhi = prev_d[idx][ridx], f.dist[ridx]  # (J,), (J,)
            rb = lb[ridx]  # (J,)
            ro, rd = ok[ridx], dk[ridx]  # (J, 3), (J, 3)
            for _ in range(REFINE_ITERATIONS):
                mid = 0.5 * (lo + hi)  # (J,)
                pm = ro + mid[:, None] * rd  # (J, 3)
                fm = field_at(rs, pm, cells_at(rs, pm))
                rb = torch.where(fm.brick >= 0, fm.brick, rb)
                neg = fm.solid | (fm.dist < 0)  # (J,)
                hi, fhi = torch.where(neg, mid, hi), torch.where(neg, fm.dist, fhi)
                lo, flo = torch.where(neg, lo, mid), torch.where(neg, flo, fm.dist)
            denom = flo - fhi  # (J,)
            secant = torch.where(denom > 0, lo + (hi - lo) * (flo / denom), lo)  # (J,)
            hit_t[ridx] = secant
            lb[ridx] = rb
            last_brick[idx] = lb
        threshold = eps[idx] + slope * tk  # (K,) voxels (one multiply-add on the device)
        pd, pt = prev_d[idx], prev_t[idx]  # (K,), (K,) the previous sample
        near = ~f.far_free & (f.dist < threshold) & (f.dist <= pd) & ~inside  # (K,)
        if bool(near.any()):  # where the line through the last two samples meets zero (settle_hit)
            run = torch.minimum(f.dist * (tk - pt) / (pd - f.dist), SECANT_REACH * f.dist)  # (K,)
            stop = torch.minimum(torch.where(f.dist < pd, tk + run, tk), t1[idx])  # (K,)
            hit_t = torch.where(near, stop, hit_t)
        hit = inside | near  # (K,)
        hidx = idx[hit]
        depth[hidx] = hit_t[hit] * sk.voxel[hit]
        semantic[hidx] = semantic_of(lb[hit])
        active[hidx] = False

        go = ~hit  # (K,)
        nxt = tk + torch.maximum(f.dist, eps[idx])  # (K,)
        far = go & f.far_free  # (K,)
        if bool(far.any()):
            edge = torch.ones_like(f.shift) << f.shift  # (K,)
            te = [exit_time(ok[:, k], dk[:, k], inv[idx][:, k], f.corner[:, k], edge) for k in range(3)]
            t_exit = torch.minimum(torch.minimum(te[0], te[1]), te[2])  # (K,)
            # the bound past the exit (max(d, eps): progress even where rounding keeps p in the cube);
            # an exit through a face of the scene's cube is that axis' slab exit, so this passes t1
            nxt = torch.where(far, torch.maximum(t_exit, tk) + torch.maximum(f.dist, eps[idx]), nxt)
        gidx = idx[go]
        prev_t[gidx] = tk[go]
        prev_d[gidx] = f.dist[go]
        t[gidx] = nxt[go]
        beyond = go & (nxt > t1[idx])  # (K,)
        active[idx[beyond]] = False

    out_of_steps = active  # (M,) rays still running after max_steps
    depth[out_of_steps] = torch.minimum(t[out_of_steps] * s.voxel[out_of_steps], horizon32)
    # A ray the walk ended without a hit reports the first primitive within the horizon.
    to_prim = (semantic == 0) & ~out_of_steps & (prim_t <= p.horizon) & torch.isfinite(depth)  # (M,)
    depth = torch.where(to_prim, prim_t.float(), depth)
    semantic = torch.where(to_prim, prim_sem, semantic)
    out_depth.copy_(depth.view(b, r))
    if out_semantic is not None:
        out_semantic.copy_(
            semantic.clamp(max=255 if out_semantic.dtype == torch.uint8 else 2**31 - 1).view(b, r)
        )
    if out_steps is not None:
        out_steps.copy_(steps.view(b, r))


def sample_distance_ref(
    scenes: SceneCorpus,
    scene_ids: torch.Tensor,
    points: torch.Tensor,
    out: torch.Tensor | None = None,
    *,
    prims: torch.Tensor | None = None,
    prim_world: torch.Tensor | None = None,
    prim_owner: torch.Tensor | None = None,
) -> torch.Tensor:
    """Reference twin of `navi_env.tracer.trace.sample_distance` (primitive distances in float64)."""
    n, _, _ = validate_sample(scenes, scene_ids, points, out, prims, prim_world, prim_owner)
    sid = scene_ids.long()  # (N,)
    ok = (sid >= 0) & (sid < len(scenes))  # (N,)
    s = ref_scene(scenes, sid.clamp(0, len(scenes) - 1))
    p = (points - s.origin) * s.inv_voxel[:, None]  # (N, 3) voxel space
    res = s.resolution.to(F32)[:, None]  # (N, 1)
    zero = torch.zeros_like(p)
    e = torch.maximum(torch.maximum(0.0 - p, p - res), zero)  # (N, 3)
    square = e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1] + e[:, 2] * e[:, 2]  # (N,) float32
    # torch's float32 sqrt is not correctly rounded on every CPU; the float64 one, rounded once, is.
    outside_dist = torch.sqrt(square.double()).float() * s.voxel  # (N,)
    field = field_at(s, p, cells_at(s, p)).dist * s.voxel  # (N,)
    outside = (e > 0).any(dim=1)  # (N,)
    result = torch.where(outside, outside_dist, field)  # (N,)
    if prims is not None and prim_world is not None and prims.shape[1] > 0:
        near = prim_distance_ref(prims, prim_world, points, prim_owner)  # (N,) float64
        result = torch.minimum(result, near.clamp(max=3.0e38).float().to(result.device))
    result = torch.where(ok & torch.isfinite(p).all(dim=1), result, torch.full_like(result, float("nan")))
    if out is None or n == 0:
        return result if out is None else out
    out.copy_(result)
    return out
