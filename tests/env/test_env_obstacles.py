"""Dynamic primitives traced in the same pass as the static scene (navi_env.tracer.primitives).

The kernel's ray-primitive hits and distances match the float64 twins; the twins agree with each
other (a hit lies on the surface the distance describes, and the ray is free before it); moving the
primitives every step needs no rebuild and keeps CPU, CUDA and the reference in agreement.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from navi_env.rays import spherical_directions, tiled_ray_order
from navi_env.tracer import primitives as ob
from navi_env.tracer import trace as navi_trace
from navi_env.tracer.analytic_scenes import AnalyticScene, Box, demo_room, free_points, random_directions
from navi_env.tracer.scene import SceneCorpus, load_corpus
from navi_env.tracer.trace import sample_distance, trace
from navi_env.tracer.trace_ref import sample_distance_ref, trace_ref

gpu = pytest.mark.gpu  # skipped without CUDA by tests/conftest.py
HORIZON = 30.0


def _random_prims(worlds: int, per_world: int, lo: np.ndarray, hi: np.ndarray, seed: int) -> torch.Tensor:
    """(W, K, 16) records of every kind (and some empty slots) placed inside [lo, hi]."""
    rng = np.random.default_rng(seed)
    recs = []
    for w in range(worlds):
        for k in range(per_world):
            c = rng.uniform(lo, hi).tolist()
            kind = (w + k) % 5
            if kind == ob.NONE:
                recs.append(torch.zeros(ob.WORDS))
            elif kind == ob.SPHERE:
                recs.append(ob.record(ob.SPHERE, c, radius=float(rng.uniform(0.2, 1.2)), cls=6))
            elif kind == ob.CAPSULE:
                recs.append(ob.record(ob.CAPSULE, c, radius=0.3, axis=rng.normal(0, 0.8, 3).tolist(), cls=9))
            elif kind == ob.BOX:
                recs.append(ob.record(ob.BOX, c, axis=rng.uniform(0.05, 1.0, 3).tolist(), cls=10))
            else:
                recs.append(
                    ob.record(
                        ob.OBB, c, axis=rng.uniform(0.05, 1.0, 3).tolist(), quat=rng.normal(size=4).tolist()
                    )
                )
    return torch.stack(recs).reshape(worlds, per_world, ob.WORDS).contiguous()  # (W, K, 16)


def test_reference_hits_lie_on_the_surface_and_the_ray_is_free_before() -> None:
    rng = np.random.default_rng(0)
    prims = _random_prims(1, 40, np.zeros(3), np.full(3, 6.0), seed=1)[0]  # (K, 16)
    checked = 0
    for rec in prims.double().tolist():
        if int(rec[ob.KIND]) == ob.NONE:
            continue
        for _ in range(60):
            o = rng.uniform(-4.0, 10.0, 3).tolist()
            aim = np.array(rec[ob.CENTER : ob.CENTER + 3]) + rng.normal(0.0, 0.6, 3)  # mostly hits
            d = aim - np.array(o)
            d = (d / np.linalg.norm(d)).tolist()
            t = ob.hit_one(rec, o, d)
            inside = ob.distance_one(rec, o) <= 0.0
            assert (t == 0.0) == inside
            if math.isinf(t) or t == 0.0:
                samples = np.linspace(0.0, 20.0, 400)
            else:
                p = [o[k] + t * d[k] for k in range(3)]
                assert abs(ob.distance_one(rec, p)) < 1e-9, ob.KIND_NAMES[int(rec[ob.KIND])]
                samples = np.linspace(0.0, t, 200)[:-1]
                checked += 1
            if not inside:
                free = [ob.distance_one(rec, [o[k] + s * d[k] for k in range(3)]) for s in samples]
                assert min(free) > -1e-9  # nothing entered before the reported hit
    assert checked > 100


def test_distance_twins_of_every_kind() -> None:
    sphere = ob.record(ob.SPHERE, (1, 2, 3), radius=0.5).tolist()
    assert ob.distance_one(sphere, (1, 2, 4)) == pytest.approx(0.5)
    capsule = ob.record(ob.CAPSULE, (0, 0, 0), radius=0.25, axis=(1, 0, 0)).tolist()
    assert ob.distance_one(capsule, (0.5, 1, 0)) == pytest.approx(0.75)
    assert ob.distance_one(capsule, (2, 0, 0)) == pytest.approx(0.75)
    box = ob.record(ob.BOX, (0, 0, 0), axis=(1, 2, 3)).tolist()
    assert ob.distance_one(box, (0, 0, 0)) == pytest.approx(-1.0)
    assert ob.distance_one(box, (2, 3, 0)) == pytest.approx(math.sqrt(2))
    quarter = (math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4))  # 90 degrees about +Z
    obb = ob.record(ob.OBB, (0, 0, 0), axis=(1, 2, 3), quat=quarter).tolist()
    assert ob.distance_one(obb, (1.5, 0, 0)) == pytest.approx(-0.5, abs=1e-6)  # x now spans +-2
    assert ob.distance_one(obb, (0, 1.5, 0)) == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(ValueError):
        ob.record(ob.SPHERE, (0, 0, 0), radius=0.0)
    with pytest.raises(ValueError):
        ob.record(ob.BOX, (0, 0, 0), axis=(1, 0, 1))


def _scene() -> AnalyticScene:
    return AnalyticScene(
        (Box((1.0, 1.5, 0.5), (3.0, 6.0, 2.5)), Box((4.5, 0.7, 1.0), (7.2, 2.1, 7.0))),
        resolution=32,
        voxel_size=0.25,
    )


@pytest.fixture(scope="module")
def setting() -> tuple[list[AnalyticScene], SceneCorpus]:
    scenes = [_scene(), demo_room(32, 8.0)]
    return scenes, load_corpus([s.gmdag() for s in scenes])


def _step_inputs(
    scenes: list[AnalyticScene], per_scene: int, step: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Actors, their worlds (two actors per world) and primitives moved to this step's poses."""
    origins = [free_points(s, per_scene, 0.0, seed=10 + i) for i, s in enumerate(scenes)]  # (P, 3) each
    ids = torch.arange(len(scenes), dtype=torch.int64).repeat_interleave(per_scene)  # (B,)
    b = len(ids)
    world = (torch.arange(b, dtype=torch.int32) // 2).contiguous()  # (B,)
    prims = _random_prims((b + 1) // 2, 7, np.full(3, 0.5), np.full(3, 7.5), seed=3)  # (W, K, 16)
    drift = torch.tensor([0.37, -0.21, 0.13]) * step  # the same primitives, moved every step
    prims[:, :, ob.CENTER : ob.CENTER + 3] += drift
    prims[0, 1] = ob.record(ob.SPHERE, origins[0][0].tolist(), radius=0.4)  # an actor inside a sphere
    prims[0, 2] = ob.record(ob.SPHERE, origins[0][1].tolist(), radius=0.3, owner=1)  # actor 1's own drone
    return ids, torch.tensor(np.concatenate(origins), dtype=torch.float32), world, prims.contiguous()


def _trace(fn: object, corpus: SceneCorpus, ids: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
           horizon: float = HORIZON, **kw: object) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    b, r = len(ids), dirs.shape[-2]  # dirs (R, 3) or (B, R, 3)
    depth = torch.full((b, r), -1.0, device=origins.device)  # (B, R)
    sem = torch.full((b, r), -1, dtype=torch.int32, device=origins.device)  # (B, R)
    fn(corpus, ids, origins, dirs, out_depth=depth, out_semantic=sem, horizon=horizon, **kw)  # type: ignore[operator]
    return depth, sem


def _check_pair(
    kernel: tuple[torch.Tensor, torch.Tensor], ref: tuple[torch.Tensor, torch.Tensor], static: torch.Tensor
) -> None:
    """Depths agree to 1e-4 m; semantics agree except where the static surface and a primitive lie
    within a millimetre of each other along the ray (either may win such a tie)."""
    (d1, s1), (d2, s2) = kernel, ref
    assert float((d1.cpu() - d2).abs().max()) < 1e-4
    tie = (static - d2).abs() < 1e-3  # (B, R)
    assert torch.equal(s1.cpu()[~tie], s2[~tie])


def _check_cuda_pair(
    gpu: tuple[torch.Tensor, torch.Tensor], cpu: tuple[torch.Tensor, torch.Tensor], voxel: torch.Tensor
) -> None:
    """CUDA against the CPU (or the reference): the primitives are exact on both (hits within 1e-3 m:
    the device contracts multiply-adds), while CUDA reads the static field through the texture unit,
    whose 8-bit filter weights move a static hit by a small fraction of a voxel (docs/SDFDAG_RUNTIME.md);
    a rare grazing ray decides its hit a step apart. voxel: (B, 1) meters."""
    (d1, s1), (d2, s2) = gpu, cpu
    diff = (d1.cpu() - d2).abs()  # (B, R) meters
    close = (diff < 1e-3) | (diff < 0.1 * voxel)
    assert float(close.float().mean()) >= 0.995, float(close.float().mean())
    assert float((s1.cpu() != s2).float().mean()) <= 0.005


def test_cpu_matches_reference_with_primitives_moving_every_step(
    setting: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, corpus = setting
    dirs = torch.tensor(random_directions(96, seed=5), dtype=torch.float32)  # (R, 3)
    seen = set()
    for step in range(3):
        ids, origins, world, prims = _step_inputs(scenes, 4, step)
        static, _ = _trace(trace_ref, corpus, ids, origins, dirs)
        kernel = _trace(trace, corpus, ids, origins, dirs, prims=prims, prim_world=world)
        ref = _trace(trace_ref, corpus, ids, origins, dirs, prims=prims, prim_world=world)
        _check_pair(kernel, ref, static)
        seen |= set(kernel[1].unique().tolist())
        assert torch.all(kernel[0][0] == 0.0)  # actor 0 sits inside a sphere: every ray hits it at once
        assert float((kernel[0] < static - 1e-3).float().mean()) > 0.05  # primitives block the view
    assert {7, 10, 11}.issubset(seen)  # classes 6, 9, 10 (+1) and the static scene's codes


def test_an_actor_never_sees_its_own_primitive(setting: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    scenes, corpus = setting
    ids, origins, world, prims = _step_inputs(scenes, 4, 0)
    prims[0, :] = 0.0  # world 0 (actors 0 and 1) holds only actor 1's drone, placed below
    dirs = torch.tensor(random_directions(64, seed=6), dtype=torch.float32)  # (R, 3)
    static, _ = _trace(trace, corpus, ids, origins, dirs)
    ray = int(static[0].argmax())  # actor 0's longest free ray
    assert float(static[0, ray]) > 2.0
    center = origins[0] + dirs[ray]  # 1 m out along it
    prims[0, 0] = ob.record(ob.SPHERE, center.tolist(), radius=0.3, owner=1)
    with_drone, sem = _trace(trace, corpus, ids, origins, dirs, prims=prims, prim_world=world)
    assert float(with_drone[0, ray]) == pytest.approx(0.7, abs=1e-4)  # actor 0 sees actor 1's drone
    assert int(sem[0, ray]) == 1 + ob.OBSTACLE_CLASS
    prims[0, 0, ob.KIND] = 0.0  # remove it
    without, _ = _trace(trace, corpus, ids, origins, dirs, prims=prims, prim_world=world)
    assert torch.equal(with_drone[1], without[1])  # actor 1 never saw its own drone
    assert torch.equal(without[:2], static[:2])  # world 0, now all empty slots, changes nothing


def test_sample_distance_is_the_min_with_every_primitive(
    setting: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, corpus = setting
    ids, origins, world, prims = _step_inputs(scenes, 4, 1)
    rng = np.random.default_rng(7)
    n = 300
    pick = torch.tensor(rng.integers(0, len(ids), n))  # (N,)
    points = (origins[pick] + torch.tensor(rng.normal(0, 1.5, (n, 3)), dtype=torch.float32)).contiguous()
    sid, pw = ids[pick].contiguous(), world[pick].contiguous()  # (N,), (N,) int32
    owner = pick.to(torch.int32).contiguous()  # (N,) each point belongs to its actor
    static = sample_distance(corpus, sid, points)  # (N,)
    got = sample_distance(corpus, sid, points, prims=prims, prim_world=pw, prim_owner=owner)
    ref = sample_distance_ref(corpus, sid, points, prims=prims, prim_world=pw, prim_owner=owner)
    assert float((got - ref).abs().max()) < 1e-5
    near = ob.prim_distance_ref(prims, pw, points, owner).float()  # (N,)
    torch.testing.assert_close(got, torch.minimum(static, near), rtol=0, atol=1e-5)
    assert float((got < static - 1e-3).float().mean()) > 0.05
    with pytest.raises(ValueError, match="prim_world"):
        sample_distance(corpus, sid, points, prims=prims)


def test_bad_primitive_arguments_are_refused(setting: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    scenes, corpus = setting
    ids, origins, world, prims = _step_inputs(scenes, 2, 0)
    dirs = torch.tensor(random_directions(8, seed=1), dtype=torch.float32)  # (R, 3)
    with pytest.raises(ValueError, match="W, K, 16"):
        _trace(trace, corpus, ids, origins, dirs, prims=prims[:, :, :8].contiguous())
    with pytest.raises(TypeError):
        _trace(trace, corpus, ids, origins, dirs, prims=prims.double())
    with pytest.raises(ValueError, match="prim_world"):
        _trace(trace, corpus, ids, origins, dirs, prims=prims, prim_world=world[:1].contiguous())


def test_the_launcher_refuses_a_primitive_scratch_smaller_than_its_tables(
    setting: tuple[list[AnalyticScene], SceneCorpus], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The launch builds its primitive tables in a buffer `trace` sizes with the mirror of the header's
    prim_scratch_bytes; one word short (masks or not), the launcher refuses instead of writing past it."""
    scenes, corpus = setting
    ids, origins, world, prims = _step_inputs(scenes, 2, 0)
    dirs = torch.tensor(random_directions(300, seed=1), dtype=torch.float32)  # (R, 3): 3 ray groups
    exact = navi_trace.prim_scratch_bytes
    monkeypatch.setattr(navi_trace, "prim_scratch_bytes", lambda *a: exact(*a) - 8)
    for shared in (dirs, dirs.expand(len(ids), -1, -1).contiguous()):  # with masks, then without
        with pytest.raises(RuntimeError, match="primitive scratch"):
            _trace(trace, corpus, ids, origins, shared, prims=prims, prim_world=world)


@gpu
def test_cuda_matches_cpu_with_primitives_moving_every_step(
    setting: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, _ = setting
    cpu = load_corpus([s.gmdag() for s in scenes])
    cuda = load_corpus([s.gmdag() for s in scenes], "cuda")
    dirs = torch.tensor(random_directions(128, seed=9), dtype=torch.float32)  # (R, 3)
    for step in range(4):
        ids, origins, world, prims = _step_inputs(scenes, 6, step)
        on_cpu = _trace(trace, cpu, ids, origins, dirs, prims=prims, prim_world=world)
        on_gpu = _trace(
            trace, cuda, ids.cuda(), origins.cuda(), dirs.cuda(), prims=prims.cuda(), prim_world=world.cuda()
        )
        voxel = torch.tensor([s.voxel_size for s in scenes])[ids][:, None]  # (B, 1) meters
        _check_cuda_pair(on_gpu, on_cpu, voxel)
        pts = origins + 0.3
        d_cpu = sample_distance(cpu, ids, pts, prims=prims, prim_world=world)
        d_gpu = sample_distance(cuda, ids.cuda(), pts.cuda(), prims=prims.cuda(), prim_world=world.cuda())
        assert float(((d_gpu.cpu() - d_cpu).abs() / voxel[:, 0]).max()) < 0.02


def _extreme_points(rec: list[float]) -> list[np.ndarray]:
    """Surface points of a primitive that lie on (or nearest to) its bounding sphere: box corners,
    capsule tips, points of a sphere's surface."""
    kind = int(rec[ob.KIND])
    c, rad = np.array(rec[ob.CENTER : ob.CENTER + 3]), rec[ob.RADIUS]
    a = np.array(rec[ob.AXIS : ob.AXIS + 3])
    if kind == ob.SPHERE:
        u = np.random.default_rng(0).normal(size=(8, 3))
        return [c + rad * v / np.linalg.norm(v) for v in u]
    if kind == ob.CAPSULE:
        tip = a + rad * a / np.linalg.norm(a)
        return [c + tip, c - tip]
    corners = [np.array([sx, sy, sz]) * a for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    if kind == ob.OBB:
        w, x, y, z = rec[ob.QUAT : ob.QUAT + 4]  # box frame -> world
        m = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        corners = [m @ k for k in corners]
    return [c + k for k in corners]


def _grazing_case() -> tuple[SceneCorpus, torch.Tensor, list[torch.Tensor], list[np.ndarray]]:
    """One actor at a fixed origin and, for each primitive (every kind, 2 to 150 m away), rays aimed 1 mm
    inside and 1 cm outside its extreme points (on its bounding sphere, where a cull could go wrong)."""
    corpus = load_corpus([demo_room(32, 8.0).gmdag()])
    origin = np.array([-30.0, 4.0, 4.0])  # outside the scene's cube, facing away from it: no static hit
    prims, dirs = [], []
    for i, dist in enumerate((2.0, 20.0, 150.0)):
        for kind in (ob.SPHERE, ob.CAPSULE, ob.BOX, ob.OBB):
            u = np.random.default_rng(100 + i * 5 + kind).normal(size=3)
            u[0] = -abs(u[0]) - 1.0  # away from the cube (+x)
            c = (origin + dist * u / np.linalg.norm(u)).tolist()
            rec = ob.record(kind, c, radius=0.4, axis=(0.9, 0.3, 0.5), quat=(0.8, 0.3, -0.4, 0.2))
            aim = []
            for p in _extreme_points(rec.double().tolist()):
                out = (p - np.array(c)) / np.linalg.norm(p - np.array(c))
                aim += [p - 1e-3 * out, p + 1e-2 * out]
            d = np.stack(aim) - origin  # (R, 3)
            prims.append(rec)
            dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    return corpus, torch.tensor(origin, dtype=torch.float32)[None], prims, dirs


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=gpu)])
def test_the_bounding_sphere_cull_never_drops_a_hit(device: str) -> None:
    """Every ray first tests the primitives' bounding spheres (seen from its origin) and intersects
    exactly only those it may reach. Rays aimed just inside a primitive's extreme points (box corners,
    capsule tips: on the bounding sphere) must still hit it at the float64 depth, and rays aimed just
    outside must agree with the float64 test (most miss), at 2 to 150 m. Both paths run: K = 1 (the rays'
    group mask from their cone) and K = 70 (the primitive among empty slots; no mask, every ray tests all)."""
    corpus, origin, prims, dirs = _grazing_case()
    if device == "cuda":
        corpus = load_corpus([demo_room(32, 8.0).gmdag()], "cuda")
    misses = 0
    for rec, d in zip(prims, dirs, strict=True):
        want = [ob.hit_one(rec.double().tolist(), origin[0].double().tolist(), v.tolist()) for v in d]
        assert all(math.isfinite(t) for t in want[::2])  # the rays aimed 1 mm inside do hit (float64)
        misses += sum(math.isinf(t) for t in want[1::2])
        for k_slots in (1, 70):
            table = torch.zeros(1, k_slots, ob.WORDS)  # (1, K, 16)
            table[0, k_slots // 2] = rec
            depth, sem = _trace(
                trace, corpus, torch.zeros(1, dtype=torch.int64, device=device), origin.to(device),
                torch.tensor(d, dtype=torch.float32, device=device), prims=table.to(device), horizon=300.0,
            )  # fmt: skip
            for r, t in enumerate(want):
                if math.isinf(t):
                    assert int(sem[0, r]) != 1 + ob.OBSTACLE_CLASS
                else:
                    assert int(sem[0, r]) == 1 + ob.OBSTACLE_CLASS, (ob.KIND_NAMES[int(rec[ob.KIND])], r)
                    tol = 0.01 + 1e-3 * t  # a grazing entry depth is ill-conditioned
                    assert float(depth[0, r]) == pytest.approx(t, abs=tol)
    assert misses > 40  # most rays aimed 1 cm outside an extreme point pass it


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=gpu)])
def test_ray_group_masks_keep_every_primitive_a_ray_can_hit(
    setting: tuple[list[AnalyticScene], SceneCorpus], device: str
) -> None:
    """With shared directions a launch bounds each group of 128 work items by a cone and lets a ray
    test only the primitives whose bounding sphere may meet its group's cone (rotated by the actor's
    yaw). On the 64 x 24 sensor pattern in tiled order (12 groups), yawed actors and primitives of
    every kind 0.5 to 6 m away, the result equals the float64 reference that tests every primitive,
    with K = 12 (masks) and K = 70 (more than a mask holds: every ray tests every primitive), and with
    3 steps per ray (a ray out of steps reports the distance reached, not the primitive beyond)."""
    scenes, corpus = setting
    dirs = spherical_directions(64, 24, torch.device("cpu"))  # (R, 3)
    order = tiled_ray_order(64, 24)  # (R,)
    ids, origins, _, _ = _step_inputs(scenes, 2, 0)
    yaw = torch.tensor([0.3, -2.1, 1.7, 3.0])  # (B,)
    rng = np.random.default_rng(7)
    offsets = rng.normal(size=(len(ids), 12, 3))  # (B, 12, 3)
    offsets *= (rng.uniform(0.5, 6.0, (len(ids), 12)) / np.linalg.norm(offsets, axis=2))[..., None]
    prims = _random_prims(len(ids), 12, np.zeros(3), np.zeros(3), seed=11)  # (B, 12, 16) every kind at 0
    prims[:, :, ob.CENTER : ob.CENTER + 3] = origins[:, None, :] + torch.tensor(offsets, dtype=torch.float32)
    wide = torch.zeros(len(ids), 70, ob.WORDS)  # (B, 70, 16): the same primitives among empty slots
    wide[:, 29:41] = prims
    static, _ = _trace(trace_ref, corpus, ids, origins, dirs, yaw=yaw)
    ref = _trace(trace_ref, corpus, ids, origins, dirs, yaw=yaw, prims=prims)
    assert float((ref[0] < static - 1e-3).float().mean()) > 0.1  # the primitives fill much of the view
    # 3 steps: most walks run out before the static scene; the primitive ahead of such a ray is not reported
    short = _trace(trace_ref, corpus, ids, origins, dirs, yaw=yaw, prims=prims, max_steps=3)
    assert 0.05 < float((short[1] == 0).float().mean()) < 0.95
    dev = torch.device(device)
    if device == "cuda":
        corpus = load_corpus([s.gmdag() for s in scenes], "cuda")
    for table, steps, want in ((prims, 256, ref), (wide, 256, ref), (prims, 3, short)):
        kernel = _trace(
            trace, corpus, ids.to(dev), origins.to(dev), dirs.to(dev), yaw=yaw.to(dev), ray_order=order.to(dev),
            prims=table.contiguous().to(dev), max_steps=steps,
        )  # fmt: skip
        if device == "cuda":  # the device contracts multiply-adds and filters the static field in hardware
            _check_cuda_pair(kernel, want, torch.tensor([s.voxel_size for s in scenes])[ids][:, None])
        else:
            _check_pair(kernel, want, static)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=gpu)])
def test_rays_no_primitive_reaches_trace_as_without_primitives(
    setting: tuple[list[AnalyticScene], SceneCorpus], device: str
) -> None:
    """With primitives in one part of the view, a ray that no primitive lies along (float64, at any
    distance) reports bit for bit what the launch without primitives reports, whether its ray group's
    mask is zero (no test) or not (tests that miss): the primitive walk takes the static scene's steps
    exactly as the plain walk does. Some groups must see primitives and some none."""
    scenes, corpus = setting
    dirs = spherical_directions(64, 24, torch.device("cpu"))  # (R, 3)
    order = tiled_ray_order(64, 24)  # (R,)
    ids, origins, _, _ = _step_inputs(scenes, 2, 0)
    b = len(ids)
    rng = np.random.default_rng(13)
    ahead = np.array([1.0, 0.4, 0.1])  # (3,) every primitive lies within a narrow cone about this axis
    offsets = ahead + rng.normal(0.0, 0.08, size=(b, 8, 3))  # (B, 8, 3)
    offsets *= (rng.uniform(1.0, 4.0, (b, 8)) / np.linalg.norm(offsets, axis=2))[..., None]
    prims = _random_prims(b, 8, np.zeros(3), np.zeros(3), seed=17)  # (B, 8, 16) every kind at 0
    prims[:, :, ob.CENTER : ob.CENTER + 3] = origins[:, None, :] + torch.tensor(offsets, dtype=torch.float32)
    reach, sem = ob.prim_hit_ref(prims, torch.arange(b), origins, dirs.expand(b, -1, -1))  # (B, R) each
    clear = torch.isinf(reach)  # (B, R) no primitive along the ray
    per_group = clear[:, order].reshape(b, -1, 128)  # (B, G, 128) in work-item order
    assert bool(per_group.all(dim=2).any()) and bool((~per_group).any(dim=2).any())
    assert 0.3 < float(clear.float().mean()) < 0.99
    dev = torch.device(device)
    if device == "cuda":
        corpus = load_corpus([s.gmdag() for s in scenes], "cuda")
    args = (corpus, ids.to(dev), origins.to(dev), dirs.to(dev))
    plain = _trace(trace, *args, ray_order=order.to(dev))
    with_prims = _trace(trace, *args, ray_order=order.to(dev), prims=prims.contiguous().to(dev))
    assert torch.equal(with_prims[0].cpu()[clear], plain[0].cpu()[clear])
    assert torch.equal(with_prims[1].cpu()[clear], plain[1].cpu()[clear])
    seen = with_prims[1].cpu()[~clear] == sem[~clear]  # rays with a primitive along them: most see it first
    assert float(seen.float().mean()) > 0.5
