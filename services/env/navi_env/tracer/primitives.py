"""Dynamic primitives: spheres, capsules and boxes that move without any rebuild of the static scene.

A signed distance field composes by min, so the tracer (csrc/primitives.h) reads, beside the static
.gmdag corpus, a (W, K, 16) float32 tensor of primitive records: W worlds of K slots each. Actor b's
rays see the primitives of its world (`prim_world[b]`, or world b) and leave out the primitive whose
owner is b (its own drone); a ray reports the first primitive it enters (exact ray-primitive
intersection in the same kernel, with semantic 1 + the primitive's class) when that comes before the
static surface, and point queries return min(static field, every primitive's exact distance).

Record words (`PrimWord` in the header): kind, class, owner, radius, centre (3), axis / half extents
(3), quaternion w x y z (4, oriented boxes: box frame -> world), 2 spare. Small integers are stored
as floats. Letters: W worlds, K slots per world, M points or rays, B actors.

`prim_distance_ref` and `prim_hit_ref` are the slow twins (Python floats in float64, one primitive at
a time) of the kernel's `prim_distance` and `prim_hit`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

WORDS = 16
KIND, CLASS, OWNER, RADIUS, CENTER, AXIS, QUAT = 0, 1, 2, 3, 4, 7, 10
NONE, SPHERE, CAPSULE, BOX, OBB = 0, 1, 2, 3, 4
KIND_NAMES = {NONE: "none", SPHERE: "sphere", CAPSULE: "capsule", BOX: "box", OBB: "obb"}
OBSTACLE_CLASS = 8
"""Default class id of a moving obstacle (after the procedural scenes' 0-7): a hit reads semantic 9."""
NO_OWNER = -1.0


def record(
    kind: int,
    center: Sequence[float],
    *,
    radius: float = 0.0,
    axis: Sequence[float] = (0.0, 0.0, 0.0),
    quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
    cls: int = OBSTACLE_CLASS,
    owner: int = -1,
) -> torch.Tensor:
    """One primitive record (16,) float32. axis: the capsule's half segment vector or a box's half
    extents; quat: an oriented box's rotation (normalised here)."""
    if kind not in KIND_NAMES:
        raise ValueError(f"unknown primitive kind {kind}; kinds are {KIND_NAMES}")
    q = torch.tensor(quat, dtype=torch.float64)  # (4,)
    if kind == OBB:
        norm = float(q.norm())
        if not norm > 0.0:
            raise ValueError("an oriented box needs a non-zero quaternion")
        q = q / norm
    if kind in (SPHERE, CAPSULE) and not radius > 0.0:
        raise ValueError(f"a {KIND_NAMES[kind]} needs a positive radius, got {radius}")
    if kind in (BOX, OBB) and not all(a > 0.0 for a in axis):
        raise ValueError(f"a box needs positive half extents, got {tuple(axis)}")
    r = torch.zeros(WORDS, dtype=torch.float32)  # (16,)
    r[KIND], r[CLASS], r[OWNER], r[RADIUS] = float(kind), float(cls), float(owner), float(radius)
    r[CENTER : CENTER + 3] = torch.tensor(center, dtype=torch.float32)
    r[AXIS : AXIS + 3] = torch.tensor(axis, dtype=torch.float32)
    r[QUAT : QUAT + 4] = q.float()
    return r


def check_prims(
    prims: torch.Tensor | None, prim_world: torch.Tensor | None, count: int, device: torch.device, what: str
) -> tuple[int, int]:
    """Validate a (W, K, 16) float32 record tensor and its (count,) int32 world index; returns (W, K)."""
    if prims is None:
        if prim_world is not None:
            raise ValueError("prim_world was given without prims")
        return 0, 0
    if not isinstance(prims, torch.Tensor) or prims.dtype != torch.float32 or prims.dim() != 3:
        raise TypeError("prims must be a (W, K, 16) float32 tensor")
    if prims.shape[2] != WORDS:
        raise ValueError(f"prims must be (W, K, {WORDS}), got {tuple(prims.shape)}")
    if prims.device != device or not prims.is_contiguous():
        raise ValueError(f"prims must be contiguous on {device}")
    if prim_world is not None:
        if prim_world.dtype != torch.int32 or tuple(prim_world.shape) != (count,):
            raise ValueError(f"prim_world must be ({count},) int32 ({what})")
        if prim_world.device != device or not prim_world.is_contiguous():
            raise ValueError(f"prim_world must be contiguous on {device}")
    return int(prims.shape[0]), int(prims.shape[1])


def distance(rec: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Exact signed distance (...,) from points p (..., 3) to the primitives of records rec (..., 16)
    (broadcast; +inf for kind none). Torch ops on any device: the env's obstacle motion and sweeps use
    it; `distance_one` is its slow twin."""
    kind = rec[..., KIND]  # (...,)
    c, a = rec[..., CENTER : CENTER + 3], rec[..., AXIS : AXIS + 3]  # (..., 3), (..., 3)
    rad = rec[..., RADIUS]  # (...,)
    v = p - c  # (..., 3)
    sphere = v.norm(dim=-1) - rad  # (...,)
    aa = (a * a).sum(-1)  # (...,)
    s = ((v * a).sum(-1) / aa.clamp_min(1e-30)).clamp(-1.0, 1.0)  # (...,)
    capsule = (v - s[..., None] * a).norm(dim=-1) - rad  # (...,)
    w, u = rec[..., QUAT], rec[..., QUAT + 1 : QUAT + 4]  # (...,), (..., 3)
    uv = torch.cross(u, v, dim=-1)  # (..., 3)
    local = v - 2.0 * w[..., None] * uv + 2.0 * torch.cross(u, uv, dim=-1)  # (..., 3) R^T v
    local = torch.where((kind == OBB)[..., None], local, v)  # (..., 3)
    d = local.abs() - a  # (..., 3)
    box = d.clamp_min(0.0).norm(dim=-1) + d.amax(-1).clamp_max(0.0)  # (...,)
    out = torch.where(kind == SPHERE, sphere, torch.where(kind == CAPSULE, capsule, box))  # (...,)
    return torch.where(kind == NONE, torch.full_like(out, math.inf), out)


def bounding_radius(rec: torch.Tensor) -> torch.Tensor:
    """Radius (...,) of a sphere about the centre that holds the primitive of records rec (..., 16)."""
    kind, rad = rec[..., KIND], rec[..., RADIUS]  # (...,)
    a = rec[..., AXIS : AXIS + 3].norm(dim=-1)  # (...,)
    out = torch.where(kind == SPHERE, rad, torch.where(kind == CAPSULE, a + rad, a))  # (...,)
    return torch.where(kind == NONE, torch.zeros_like(out), out)


# ------------------------------------------------------------------------------------------------
# Slow twins: one primitive, Python floats.


def _rotate_inverse(q: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    """v rotated by the conjugate of unit quaternion q = (w, x, y, z), as a 3x3 matrix product."""
    w, x, y, z = q
    m = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )  # box frame -> world; its transpose maps world -> box frame
    return (
        m[0][0] * v[0] + m[1][0] * v[1] + m[2][0] * v[2],
        m[0][1] * v[0] + m[1][1] * v[1] + m[2][1] * v[2],
        m[0][2] * v[0] + m[1][2] * v[1] + m[2][2] * v[2],
    )


def _fields(r: Sequence[float]) -> tuple[int, list[float], float, list[float], list[float]]:
    return (
        int(r[KIND]),
        list(r[CENTER : CENTER + 3]),
        r[RADIUS],
        list(r[AXIS : AXIS + 3]),
        list(r[QUAT : QUAT + 4]),
    )


def distance_one(r: Sequence[float], p: Sequence[float]) -> float:
    """Exact signed distance (m) from point p to the primitive of record r (inf for kind none)."""
    kind, c, rad, a, q = _fields(r)
    v = [p[k] - c[k] for k in range(3)]
    if kind == SPHERE:
        return math.dist(p, c) - rad
    if kind == CAPSULE:
        aa = sum(x * x for x in a)
        s = min(max(sum(v[k] * a[k] for k in range(3)) / aa, -1.0), 1.0) if aa > 0 else 0.0
        return math.dist(v, [s * x for x in a]) - rad
    if kind in (BOX, OBB):
        local = _rotate_inverse(q, v) if kind == OBB else v
        d = [abs(local[k]) - a[k] for k in range(3)]
        outside = math.sqrt(sum(max(x, 0.0) ** 2 for x in d))
        return outside + min(max(d), 0.0)
    return math.inf


def _sphere_hit(o: Sequence[float], d: Sequence[float], c: Sequence[float], rad: float) -> float:
    oc = [o[k] - c[k] for k in range(3)]
    cc = sum(x * x for x in oc) - rad * rad
    if cc <= 0:
        return 0.0
    b = sum(oc[k] * d[k] for k in range(3))
    disc = b * b - cc
    if disc < 0 or b > 0:
        return math.inf
    return -b - math.sqrt(disc)


def _box_hit(o: Sequence[float], d: Sequence[float], h: Sequence[float]) -> float:
    t0, t1 = 0.0, math.inf
    for k in range(3):
        if d[k] != 0:
            ta, tb = (-h[k] - o[k]) / d[k], (h[k] - o[k]) / d[k]
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        elif abs(o[k]) > h[k]:
            return math.inf
    return t0 if t0 <= t1 else math.inf


def hit_one(r: Sequence[float], o: Sequence[float], d: Sequence[float]) -> float:
    """Entry distance (m) of the ray o + t d (t >= 0, |d| = 1) into the primitive; 0 from inside;
    inf when it misses."""
    kind, c, rad, a, q = _fields(r)
    if kind == SPHERE:
        return _sphere_hit(o, d, c, rad)
    if kind == CAPSULE:
        ends = [[c[k] - a[k] for k in range(3)], [c[k] + a[k] for k in range(3)]]
        best = min(_sphere_hit(o, d, e, rad) for e in ends)
        # The cylinder: points whose projection on the axis lies within the segment, at distance rad.
        axis = [2 * x for x in a]
        length2 = sum(x * x for x in axis)
        if length2 > 0:
            u = [x / math.sqrt(length2) for x in axis]
            oa = [o[k] - ends[0][k] for k in range(3)]
            along_o = sum(oa[k] * u[k] for k in range(3))
            along_d = sum(d[k] * u[k] for k in range(3))
            po = [oa[k] - along_o * u[k] for k in range(3)]  # perpendicular parts
            pd = [d[k] - along_d * u[k] for k in range(3)]
            qa = sum(x * x for x in pd)
            qb = sum(po[k] * pd[k] for k in range(3))
            qc = sum(x * x for x in po) - rad * rad
            if qc <= 0 and 0 <= along_o <= math.sqrt(length2):
                return 0.0
            if qa > 0 and qb * qb - qa * qc >= 0:
                t = (-qb - math.sqrt(qb * qb - qa * qc)) / qa
                if t >= 0 and 0 <= along_o + t * along_d <= math.sqrt(length2):
                    best = min(best, t)
        return best
    if kind == BOX:
        return _box_hit([o[k] - c[k] for k in range(3)], d, a)
    if kind == OBB:
        return _box_hit(_rotate_inverse(q, [o[k] - c[k] for k in range(3)]), _rotate_inverse(q, d), a)
    return math.inf


def prim_distance_ref(
    prims: torch.Tensor, world: torch.Tensor, points: torch.Tensor, owner: torch.Tensor | None = None
) -> torch.Tensor:
    """min over the world's primitives of their distance (M,) float64 at points (M, 3); inf where a
    world has none (or is out of range); `owner` (M,) leaves out each point's own primitive."""
    recs = prims.double().cpu().tolist()  # [W][K][16]
    out = []
    for m, p in enumerate(points.double().cpu().tolist()):
        w = int(world[m])
        me = -2 if owner is None else int(owner[m])
        best = math.inf
        if 0 <= w < len(recs):
            for r in recs[w]:
                if int(r[KIND]) != NONE and int(r[OWNER]) != me:
                    best = min(best, distance_one(r, p))
        out.append(best)
    return torch.tensor(out, dtype=torch.float64)  # (M,)


def prim_hit_ref(
    prims: torch.Tensor, world: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """First primitive hit of B actors x R rays: (B, R) float64 distance (inf if none) and (B, R) int64
    semantic (1 + class, 0 if none). origins (B, 3); directions (B, R, 3) unit, world frame. Actor b
    leaves out the primitive it owns."""
    recs = prims.double().cpu().tolist()  # [W][K][16]
    b_count, r_count = directions.shape[0], directions.shape[1]
    dist = torch.full((b_count, r_count), math.inf, dtype=torch.float64)  # (B, R)
    sem = torch.zeros(b_count, r_count, dtype=torch.int64)  # (B, R)
    dirs = directions.double().cpu().tolist()
    for b, o in enumerate(origins.double().cpu().tolist()):
        w = int(world[b])
        if not 0 <= w < len(recs):
            continue
        for r in range(r_count):
            for rec in recs[w]:
                if int(rec[KIND]) == NONE or int(rec[OWNER]) == b:
                    continue
                t = hit_one(rec, o, dirs[b][r])
                if t < dist[b, r]:
                    dist[b, r] = t
                    sem[b, r] = 1 + int(rec[CLASS])
    return dist, sem


def scatter(
    origins: torch.Tensor, per_world: int, gen: torch.Generator, near: float = 1.0, far: float = 8.0
) -> torch.Tensor:
    """(B, K, 16) records for K primitives around each of B points (B, 3): kinds cycle through sphere,
    capsule, box and oriented box, centres 1-8 m away in random directions, sizes 0.2-1 m (benchmarks
    and tests; one world per point). Drawn on the CPU from `gen`, returned on origins' device."""
    b, k = origins.shape[0], per_world
    dirs = torch.randn(b, k, 3, generator=gen)  # (B, K, 3)
    dirs = dirs / dirs.norm(dim=2, keepdim=True).clamp_min(1e-6)
    dist = near + (far - near) * torch.rand(b, k, 1, generator=gen)  # (B, K, 1)
    rec = torch.zeros(b, k, WORDS)  # (B, K, 16)
    kinds = torch.tensor([SPHERE, CAPSULE, BOX, OBB], dtype=torch.float32)[torch.arange(k) % 4]  # (K,)
    rec[:, :, KIND] = kinds
    rec[:, :, CLASS] = float(OBSTACLE_CLASS)
    rec[:, :, OWNER] = NO_OWNER
    rec[:, :, RADIUS] = 0.2 + 0.8 * torch.rand(b, k, generator=gen)
    rec[:, :, CENTER : CENTER + 3] = origins.cpu()[:, None, :] + dirs * dist
    size = 0.2 + 0.8 * torch.rand(b, k, 3, generator=gen)  # (B, K, 3)
    capsule = (kinds == CAPSULE)[None, :, None]  # (1, K, 1)
    rec[:, :, AXIS : AXIS + 3] = torch.where(capsule, size - 0.6, size)  # capsule: a half segment
    quat = torch.randn(b, k, 4, generator=gen)  # (B, K, 4)
    rec[:, :, QUAT : QUAT + 4] = quat / quat.norm(dim=2, keepdim=True).clamp_min(1e-6)
    return rec.to(origins.device).contiguous()
