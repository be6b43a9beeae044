"""The compiled tracer takes the same steps as trace_ref (CPU here, CUDA on a GPU host)."""

from __future__ import annotations

import dataclasses
import gc
import math
from collections.abc import Callable

import numpy as np
import pytest
import torch

from navi_env.rays import spherical_directions, tiled_ray_order
from navi_env.tracer import primitives
from navi_env.tracer.analytic_scenes import (
    AnalyticScene,
    Box,
    Sphere,
    demo_room,
    free_points,
    random_directions,
)
from navi_env.tracer.scene import SceneCorpus, load_corpus
from navi_env.tracer.trace import sample_distance, trace
from navi_env.tracer.trace_ref import sample_distance_ref, trace_ref

REL_TOL = 1e-4
gpu = pytest.mark.gpu  # skipped without CUDA by tests/conftest.py


def _scenes() -> list[AnalyticScene]:
    ball = AnalyticScene(
        (Sphere((5.1, 4.3, 3.9), 2.6),), resolution=16, voxel_size=0.5, origin=(-0.5, 0.2, 0.0)
    )
    boxes = AnalyticScene(
        (Box((1.0, 1.5, 0.5), (3.0, 6.0, 2.5)), Box((4.5, 0.7, 1.0), (7.2, 2.1, 7.0))),
        resolution=32,
        voxel_size=0.25,
    )
    sparse = AnalyticScene((Sphere((21.0, 12.0, 9.5), 2.5),), resolution=64, voxel_size=0.5)  # far codes
    return [ball, boxes, demo_room(32, 8.0), sparse]


@pytest.fixture(scope="module")
def corpus() -> tuple[list[AnalyticScene], SceneCorpus]:
    scenes = _scenes()
    return scenes, load_corpus([s.gmdag() for s in scenes])


def _batch(scenes: list[AnalyticScene], per_scene: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    origins = [free_points(s, per_scene, 0.0, seed=seed + i) for i, s in enumerate(scenes)]  # (P, 3) each
    ids = torch.arange(len(scenes), dtype=torch.int64).repeat_interleave(per_scene)  # (B,)
    return ids, torch.tensor(np.concatenate(origins), dtype=torch.float32)  # (B,), (B, 3)


def _run(fn: object, corpus: SceneCorpus, ids: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
         **kw: object) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    b, r = len(ids), dirs.shape[-2]
    depth = torch.full((b, r), -1.0, device=origins.device)  # (B, R) float32
    sem = torch.full((b, r), -1, dtype=torch.int32, device=origins.device)  # (B, R) int32
    steps = torch.full((b, r), -1, dtype=torch.int32, device=origins.device)  # (B, R) int32
    fn(corpus, ids, origins, dirs, out_depth=depth, out_semantic=sem, out_steps=steps, **kw)  # type: ignore[operator]
    return depth, sem, steps


def _assert_close(a: torch.Tensor, b: torch.Tensor) -> None:
    rel = (a - b).abs() / b.abs().clamp(min=1e-3)  # (B, R)
    assert float(rel.max()) <= REL_TOL, f"max relative difference {float(rel.max()):.3g}"


@pytest.mark.parametrize("hit_slope", [0.0, 0.03])
def test_cpu_matches_reference_with_shared_directions(
    corpus: tuple[list[AnalyticScene], SceneCorpus], hit_slope: float
) -> None:
    scenes, c = corpus
    ids, origins = _batch(scenes, 6, seed=1)  # (B,), (B, 3)
    dirs = torch.tensor(random_directions(160, seed=2), dtype=torch.float32)  # (R, 3)
    kw = {"max_steps": 200, "horizon": 30.0, "hit_slope": hit_slope}
    d1, s1, n1 = _run(trace, c, ids, origins, dirs, **kw)
    d2, s2, n2 = _run(trace_ref, c, ids, origins, dirs, **kw)
    _assert_close(d1, d2)
    assert torch.equal(s1, s2) and torch.equal(n1, n2)
    assert 0.2 < float((s1 > 0).float().mean()) < 1.0  # the batch holds hits and misses
    assert float((d1 == 30.0).float().mean()) > 0.0
    if hit_slope > 0:  # the growing threshold stops rays sooner than the fixed one
        fixed = _run(trace, c, ids, origins, dirs, max_steps=200, horizon=30.0)[2]
        assert float(n1.float().mean()) < float(fixed.float().mean())


def test_cpu_matches_reference_from_outside_the_cube(corpus: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    scenes, c = corpus
    rng = np.random.default_rng(20)
    ids = torch.arange(len(scenes), dtype=torch.int64).repeat_interleave(4)  # (B,)
    lo = np.array([scenes[i].origin for i in ids.tolist()])  # (B, 3)
    hi = np.array([scenes[i].cube_max for i in ids.tolist()])  # (B, 3)
    origins = torch.tensor(rng.uniform(lo - (hi - lo), hi + (hi - lo)), dtype=torch.float32)  # (B, 3)
    dirs = torch.tensor(random_directions(300, seed=21), dtype=torch.float32)  # (R, 3)
    d1, s1, n1 = _run(trace, c, ids, origins, dirs, horizon=200.0)
    d2, s2, n2 = _run(trace_ref, c, ids, origins, dirs, horizon=200.0)
    _assert_close(d1, d2)
    assert torch.equal(s1, s2) and torch.equal(n1, n2)
    assert float((s1 > 0).float().mean()) > 0.01


def test_cpu_matches_reference_with_per_actor_directions_and_yaw(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, c = corpus
    ids, origins = _batch(scenes, 4, seed=3)  # (B,), (B, 3)
    b = len(ids)
    dirs = torch.tensor(random_directions(b * 100, seed=4), dtype=torch.float32).view(b, 100, 3)  # (B, R, 3)
    yaw = torch.linspace(-3.0, 3.0, b)  # (B,)
    d1, s1, n1 = _run(trace, c, ids.to(torch.int32), origins, dirs, yaw=yaw, hit_epsilon=0.02)
    d2, s2, n2 = _run(trace_ref, c, ids.to(torch.int32), origins, dirs, yaw=yaw, hit_epsilon=0.02)
    _assert_close(d1, d2)
    assert torch.equal(s1, s2) and torch.equal(n1, n2)


def _axis_directions() -> torch.Tensor:
    """(18, 3) unit directions with exact zero components: the 6 axes and the 12 diagonals of the
    coordinate planes."""
    h = math.sqrt(0.5)
    rows = [sign * np.eye(3)[a] for a in range(3) for sign in (1.0, -1.0)]
    for a, b in ((0, 1), (0, 2), (1, 2)):
        for sa, sb in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)):
            v = np.zeros(3)
            v[a], v[b] = sa * h, sb * h
            rows.append(v)
    return torch.tensor(np.array(rows), dtype=torch.float32)  # (18, 3)


def test_cpu_rays_along_axes_and_coordinate_planes_match_the_reference(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    """A ray with a zero direction component never leaves a far cube through the faces it runs
    along: the far step takes kBig as that axis' exit time. Such rays take the reference's steps,
    and in the sparse scene (mostly far cubes) they cross it in a few far steps each."""
    scenes, c = corpus
    ids, origins = _batch(scenes, 25, seed=22)  # (B,), (B, 3)
    dirs = _axis_directions()  # (R, 3)
    d1, s1, n1 = _run(trace, c, ids, origins, dirs, horizon=100.0)
    d2, s2, n2 = _run(trace_ref, c, ids, origins, dirs, horizon=100.0)
    _assert_close(d1, d2)
    assert torch.equal(s1, s2) and torch.equal(n1, n2)
    assert 0.1 < float((s1 > 0).float().mean()) < 1.0  # the batch holds hits and misses
    sparse = ids == 3  # (B,)
    crossing = n1[sparse].float()  # (P, R) steps out of a 32 m cube of 0.5 m voxels (2.1 on average)
    assert float(crossing.mean()) < 4.0


def test_yaw_equals_pre_rotated_directions(corpus: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    scenes, c = corpus
    ids, origins = _batch(scenes, 4, seed=5)  # (B,), (B, 3)
    dirs = torch.tensor(random_directions(150, seed=6), dtype=torch.float32)  # (R, 3)
    b = len(ids)
    yaw = torch.linspace(-2.5, 6.0, b)  # (B,)
    cos, sin = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]  # (B, 1) each
    x, y = dirs[None, :, 0], dirs[None, :, 1]  # (1, R) each
    rotated = torch.stack(
        [cos * x - sin * y, sin * x + cos * y, dirs[None, :, 2].expand(b, -1)], dim=-1
    )  # (B, R, 3)
    d1, s1, _ = _run(trace, c, ids, origins, dirs, yaw=yaw)
    d2, s2, _ = _run(trace, c, ids, origins, rotated.contiguous())
    # cos/sin may round differently in the kernel than in torch: allow a rare last-step difference.
    close = (d1 - d2).abs() <= REL_TOL * d2.abs().clamp(min=1e-3)  # (B, R)
    assert float(close.float().mean()) >= 0.999
    assert float((d1 - d2).abs().max()) <= 0.1 * 0.5  # at most ~one hit epsilon of the coarsest scene
    assert float((s1 != s2).float().mean()) <= 0.001


def test_one_launch_over_many_scenes_equals_one_launch_per_scene(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, c = corpus
    ids, origins = _batch(scenes, 5, seed=7)  # (B,), (B, 3)
    dirs = torch.tensor(random_directions(64, seed=8), dtype=torch.float32)  # (R, 3)
    together, _, _ = _run(trace, c, ids, origins, dirs)
    for i, s in enumerate(scenes):
        alone = load_corpus([s.gmdag()])
        rows = ids == i  # (B,)
        d, _, _ = _run(trace, alone, torch.zeros(int(rows.sum()), dtype=torch.int64), origins[rows], dirs)
        assert torch.equal(d, together[rows])


def test_ray_order_changes_the_schedule_not_the_results(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, c = corpus
    ids, origins = _batch(scenes, 3, seed=30)  # (B,), (B, 3)
    dirs = spherical_directions(16, 4)  # (R, 3)
    order = tiled_ray_order(16, 4, 4, 2)  # (R,)
    assert sorted(order.tolist()) == list(range(64)) and order.tolist() != list(range(64))
    plain = _run(trace, c, ids, origins, dirs)
    tiled = _run(trace, c, ids, origins, dirs, ray_order=order)
    ref = _run(trace_ref, c, ids, origins, dirs, ray_order=order)
    for a, b in zip(plain, tiled, strict=True):
        assert torch.equal(a, b)
    assert torch.equal(plain[0], ref[0])
    with pytest.raises(ValueError, match="ray_order must be a permutation"):
        _run(trace, c, ids, origins, dirs, ray_order=torch.zeros(64, dtype=torch.int32))
    with pytest.raises(TypeError, match="ray_order must be int32"):
        _run(trace, c, ids, origins, dirs, ray_order=order.long())


def test_uint8_semantic_matches_int32(corpus: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    scenes, c = corpus
    ids, origins = _batch(scenes, 3, seed=9)  # (B,), (B, 3)
    dirs = torch.tensor(random_directions(50, seed=10), dtype=torch.float32)  # (R, 3)
    d32, s32, _ = _run(trace, c, ids, origins, dirs)
    d8 = torch.empty_like(d32)  # (B, R) float32
    s8 = torch.empty(s32.shape, dtype=torch.uint8)  # (B, R) uint8
    trace(c, ids, origins, dirs, out_depth=d8, out_semantic=s8)
    assert torch.equal(d8, d32) and torch.equal(s8.to(torch.int32), s32)


def test_sample_distance_matches_reference_and_the_analytic_field(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    scenes, c = corpus
    rng = np.random.default_rng(11)
    pts, ids = [], []
    for i, s in enumerate(scenes):
        lo, hi = np.array(s.origin), s.cube_max
        pad = 0.2 * (hi - lo)
        cand = rng.uniform(lo, hi, size=(20000, 3))  # (20000, 3)
        shell = cand[np.abs(s.sdf(cand)) < 2 * s.voxel_size][:300]  # near the surface
        both = np.concatenate([rng.uniform(lo - pad, hi + pad, size=(400, 3)), shell])  # (n, 3)
        pts.append(both)
        ids.append(np.full(len(both), i))
    p = torch.tensor(np.concatenate(pts), dtype=torch.float32)  # (N, 3)
    sid = torch.tensor(np.concatenate(ids), dtype=torch.int64)  # (N,)
    got = sample_distance(c, sid, p)  # (N,)
    assert torch.equal(got, sample_distance_ref(c, sid, p))
    # Within 2 voxels of the surface on the free side the decoded field is within trilinear +
    # quantisation error of the exact one; inside solid it is negative and, in an all-solid brick (a
    # far-solid code), a bound no deeper than the exact depth.
    for i, s in enumerate(scenes):
        rows = (sid == i).numpy()
        exact = s.sdf(p[rows].double().numpy())  # (n,)
        inside = ((p[rows].numpy() > s.origin) & (p[rows].numpy() < s.cube_max)).all(axis=1)
        near = inside & (exact >= 0) & (exact < 2 * s.voxel_size)
        err = np.abs(got[rows].numpy()[near] - exact[near]) / s.voxel_size  # voxels
        assert near.sum() > 50 and np.median(err) < 0.1 and err.max() < 0.5
        deep = inside & (exact < -0.5 * s.voxel_size) & (exact > -2 * s.voxel_size)
        depth = -got[rows].numpy()[deep] / s.voxel_size  # voxels, > 0 inside solid
        assert deep.sum() > 10 and (depth > 0).all() and (depth < -exact[deep] / s.voxel_size + 0.5).all()
        outside = ~((p[rows].numpy() >= s.origin) & (p[rows].numpy() <= s.cube_max)).all(axis=1)
        assert (got[rows].numpy()[outside] > 0).all()


@gpu
def test_cuda_matches_cpu(corpus: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    """The CUDA build reads the brick atlas through the texture unit, whose trilinear weights are 8-bit
    fixed point: its field differs from the CPU's exact trilinear by a small fraction of a voxel, so
    depths agree to a tolerance in voxels, and a rare grazing ray decides its hit one step apart."""
    scenes, c = corpus
    cuda = load_corpus([s.gmdag() for s in scenes], "cuda")
    ids, origins = _batch(scenes, 40, seed=12)  # (B,), (B, 3)
    dirs = torch.tensor(random_directions(500, seed=13), dtype=torch.float32)  # (R, 3)
    yaw = torch.linspace(-3.0, 3.0, len(ids))  # (B,)
    order = tiled_ray_order(25, 20, 5, 4).cuda()  # (R,) a GPU schedule; results must not depend on it
    d1, s1, _ = _run(trace, c, ids, origins, dirs, yaw=yaw)
    d2, s2, _ = _run(trace, cuda, ids.cuda(), origins.cuda(), dirs.cuda(), yaw=yaw.cuda(), ray_order=order)
    torch.cuda.synchronize()
    voxel = torch.tensor([s.voxel_size for s in scenes])[ids][:, None]  # (B, 1) meters
    err = (d1 - d2.cpu()).abs() / voxel  # (B, R) voxels
    assert float(err.median()) <= 0.01
    assert float((err <= 0.1).float().mean()) >= 0.99
    assert float((err > 1.0).float().mean()) <= 0.002  # a hit decided one step apart
    assert float((s1 != s2.cpu()).float().mean()) <= 0.002
    p = torch.tensor(
        np.concatenate([free_points(s, 300, -1.0, seed=14) for s in scenes]), dtype=torch.float32
    )
    sid = torch.arange(len(scenes)).repeat_interleave(300)  # (N,)
    got, want = sample_distance(cuda, sid.cuda(), p.cuda()).cpu(), sample_distance(c, sid, p)  # (N,) each
    voxel_n = torch.tensor([s.voxel_size for s in scenes])[sid]  # (N,) meters
    assert float(((got - want).abs() / voxel_n).max()) <= 0.02


@gpu
def test_cuda_rays_along_axes_and_coordinate_planes_match_cpu(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    """The same axis-parallel rays on CUDA, where the cells and the far step's faces carry the
    device's bias: depths agree with the CPU to the atlas' tolerance (test_cuda_matches_cpu)."""
    scenes, c = corpus
    cuda = load_corpus([s.gmdag() for s in scenes], "cuda")
    ids, origins = _batch(scenes, 100, seed=23)  # (B,), (B, 3)
    dirs = _axis_directions()  # (R, 3)
    d1, s1, n1 = _run(trace, c, ids, origins, dirs, horizon=100.0)
    d2, s2, n2 = _run(trace, cuda, ids.cuda(), origins.cuda(), dirs.cuda(), horizon=100.0)
    torch.cuda.synchronize()
    voxel = torch.tensor([s.voxel_size for s in scenes])[ids][:, None]  # (B, 1) meters
    err = (d1 - d2.cpu()).abs() / voxel  # (B, R) voxels
    assert float(err.median()) <= 0.01
    assert float((err <= 0.1).float().mean()) >= 0.99
    assert float((s1 != s2.cpu()).float().mean()) <= 0.005
    assert float((n1 - n2.cpu()).abs().float().mean()) <= 0.05  # the same steps, but for rare grazing rays


@gpu
@pytest.mark.parametrize(("obstacles", "rays"), [(0, 32), (2, 32), (0, 1000), (2, 1000)])
def test_cuda_blocks_that_trace_several_items_change_no_output(
    corpus: tuple[list[AnalyticScene], SceneCorpus], obstacles: int, rays: int
) -> None:
    """A large CUDA launch gives a block several work items: with one ray group per actor (32 rays) a
    block traces its group for 4 actors in turn; with 8 groups (1,000 rays, the last one partial) it
    traces 6 consecutive groups of one actor, then the remaining 2. Every actor's depth, semantic and
    steps are those of a small launch, whose blocks trace one ray group of one actor."""
    scenes, _ = corpus
    cuda = load_corpus([s.gmdag() for s in scenes], "cuda")
    ids, origins = _batch(scenes, 2600, seed=40)  # (B,), (B, 3): B = 10,400
    dirs = torch.tensor(random_directions(rays, seed=41), dtype=torch.float32).cuda()  # (R, 3)
    yaw = torch.linspace(-3.0, 3.0, len(ids)).cuda()  # (B,)
    gen = torch.Generator().manual_seed(42)
    prims = primitives.scatter(origins, obstacles, gen, near=0.5, far=3.0).cuda() if obstacles else None
    ids, origins = ids.cuda(), origins.cuda()
    many = _run(trace, cuda, ids, origins, dirs, yaw=yaw, hit_slope=0.01, prims=prims)
    part = torch.arange(0, len(ids), 97, device="cuda")  # (P,) 108 actors, one per block
    few = _run(trace, cuda, ids[part], origins[part], dirs, yaw=yaw[part], hit_slope=0.01,
               prims=None if prims is None else prims[part])  # fmt: skip
    torch.cuda.synchronize()
    for a, b in zip(many, few, strict=True):
        assert torch.equal(a[part].nan_to_num(-7.0), b.nan_to_num(-7.0))
    assert float((many[1] > 0).float().mean()) > 0.3  # most rays hit a surface
    assert int(many[2].min()) >= 0  # every ray of every actor was traced


@gpu
def test_cuda_atlas_gives_the_samples_at_lattice_points(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
) -> None:
    """At a lattice point every filter weight is 0 or 1: the atlas' texel is the sample itself."""
    scenes, c = corpus
    cuda = load_corpus([s.gmdag() for s in scenes], "cuda")
    rng = np.random.default_rng(21)
    pts, sids = [], []
    for i, s in enumerate(scenes):
        cells = rng.integers(0, s.resolution + 1, size=(400, 3))  # (P, 3) lattice indices
        pts.append(np.asarray(s.origin) + cells * s.voxel_size)
        sids.append(np.full(len(cells), i))
    p = torch.tensor(np.concatenate(pts), dtype=torch.float32)  # (N, 3) meters
    sid = torch.tensor(np.concatenate(sids))  # (N,)
    got, want = sample_distance(cuda, sid.cuda(), p.cuda()).cpu(), sample_distance(c, sid, p)  # (N,) each
    voxel = torch.tensor([s.voxel_size for s in scenes])[sid]  # (N,) meters
    assert float(((got - want).abs() / voxel).max()) <= 1e-4


@gpu
def test_cuda_corpora_free_their_atlas(corpus: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    scenes, _ = corpus
    gmdags = [s.gmdag() for s in scenes] * 40
    first = load_corpus(gmdags, "cuda")  # warm-up: the library, the context, the allocator
    assert first.atlas is not None and first.device_bytes >= sum(first.nbytes)
    padding = first.atlas.nbytes - 729 * sum(info.brick_count for info in first.infos)
    assert 0 <= padding < 729 * 4**first.atlas.shift  # fewer than one slab of tiles
    del first
    gc.collect()
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    before = torch.cuda.mem_get_info()[0]
    for _ in range(5):
        held = load_corpus(gmdags, "cuda")
        size = held.atlas.nbytes if held.atlas is not None else 0
        del held
    gc.collect()
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    assert size > 1_000_000 and torch.cuda.mem_get_info()[0] >= before - size  # not five atlases held


def test_corpora_refuse_a_missing_or_foreign_atlas(corpus: tuple[list[AnalyticScene], SceneCorpus]) -> None:
    _, c = corpus
    ids, origins = torch.zeros(1, dtype=torch.int64), torch.zeros(1, 3)
    depth = torch.empty(1, 4)
    dirs = torch.tensor(random_directions(4, seed=2), dtype=torch.float32)
    fake = type("Atlas", (), {"texture": 1, "shift": 0, "device": torch.device("cuda", 0), "nbytes": 0})()
    with pytest.raises(ValueError, match="brick atlas"):
        trace(dataclasses.replace(c, atlas=fake), ids, origins, dirs, out_depth=depth)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="corner words"):
        trace_ref(dataclasses.replace(c, atlas=fake), ids, origins, dirs, out_depth=depth)  # type: ignore[arg-type]


@gpu
def test_cuda_trace_without_validation_does_not_synchronise(
    corpus: tuple[list[AnalyticScene], SceneCorpus],
    returns_before_the_gpu: Callable[[Callable[[], object]], None],
) -> None:
    """A trace never waits for the GPU, in torch or inside the extension."""
    scenes, _ = corpus
    cuda = load_corpus([s.gmdag() for s in scenes], "cuda")
    ids, origins = _batch(scenes, 8, seed=15)
    dirs = torch.tensor(random_directions(64, seed=16), dtype=torch.float32).cuda()  # (R, 3)
    depth = torch.full((len(ids), 64), math.nan, device="cuda")  # (B, R) float32
    ids, origins = ids.cuda(), origins.cuda()
    torch.cuda.set_sync_debug_mode("error")
    try:
        returns_before_the_gpu(
            lambda: trace(cuda, ids, origins, dirs, out_depth=depth, skip_direction_validation=True)
        )
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    assert bool(
        torch.isfinite(depth).all()
    )  # every ray written (it starts as NaN); values: test_cuda_matches_cpu
