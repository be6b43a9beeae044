"""Tracer edge cases: thin walls, grazing rays, origins on or inside surfaces, rays leaving the cube,
step and horizon semantics, and strict validation."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from navi_env.tracer.analytic_scenes import (
    AnalyticScene,
    Box,
    Room,
    Slab,
    demo_room,
    random_directions,
    slab_scene,
)
from navi_env.tracer.scene import SceneCorpus, load_corpus, load_scene
from navi_env.tracer.trace import trace
from navi_env.tracer.trace_ref import trace_ref

THICKNESSES = (0.25, 0.5, 1.0, 1.5, 2.0)  # voxels


def _depth(corpus: SceneCorpus, origins: np.ndarray, dirs: np.ndarray, ids: np.ndarray | None = None,
           **kw: Any) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Depth and semantic (B, R) for origins (B, 3) and dirs (R, 3) or (B, R, 3)."""
    b, r = len(origins), dirs.shape[-2]
    depth = torch.empty(b, r)  # (B, R) float32
    sem = torch.empty(b, r, dtype=torch.int32)  # (B, R) int32
    sid = torch.zeros(b, dtype=torch.int64) if ids is None else torch.tensor(ids, dtype=torch.int64)  # (B,)
    trace(corpus, sid, torch.tensor(origins, dtype=torch.float32), torch.tensor(dirs, dtype=torch.float32),
          out_depth=depth, out_semantic=sem, **kw)  # fmt: skip
    return depth.numpy(), sem.numpy()


def test_thin_walls_are_never_passed_through() -> None:
    rng = np.random.default_rng(0)
    normals = [np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), *rng.normal(size=(3, 3))]
    scenes = [slab_scene(t, n) for t in THICKNESSES for n in normals]
    # The compiler makes every surface at least a voxel thick: lattice points within h/2 are solid.
    corpus = load_corpus([s.gmdag(dilate_voxels=0.5) for s in scenes])
    per_scene, rays = 12, 120
    ids = np.repeat(np.arange(len(scenes)), per_scene)  # (B,)
    origins: list[np.ndarray] = []
    dirs: list[np.ndarray] = []
    exact: list[np.ndarray] = []
    centre = np.full(3, 16.0)  # cube centre, voxels = meters
    for s in scenes:
        slab = s.solids[0]
        assert isinstance(slab, Slab)
        n = np.array(slab.normal)
        on_plate = centre - (centre @ n - slab.offset) * n  # (3,) the cube centre projected on the plate
        side = rng.choice([-1.0, 1.0], size=(per_scene, 1))  # (P, 1) which side of the plate
        jitter = rng.uniform(-8, 8, size=(per_scene, 3))  # (P, 3)
        jitter -= (jitter @ n)[:, None] * n  # (P, 3) along the plate only
        o = on_plate + jitter + side * rng.uniform(1.5, 10.0, size=(per_scene, 1)) * n  # (P, 3)
        d = random_directions(per_scene * rays, seed=len(origins)).reshape(per_scene, rays, 3)  # (P, R, 3)
        toward = np.einsum("prk,k->pr", d, n) * side < -0.05  # (P, R) rays heading at the plate
        d = np.where(toward[..., None], d, -d)  # (P, R, 3)
        origins.append(o)
        dirs.append(d)
        exact.append(slab.hit(np.repeat(o, rays, axis=0), d.reshape(-1, 3)).reshape(per_scene, rays))
    o_all = np.concatenate(origins)  # (B, 3)
    d_all = np.concatenate(dirs)  # (B, R, 3)
    t_all = np.concatenate(exact)  # (B, R) meters = voxels
    depth, sem = _depth(corpus, o_all, d_all, ids, max_steps=2000, horizon=1000.0)
    ends = o_all[:, None, :] + t_all[..., None] * d_all  # (B, R, 3) exact hit points
    inside = ((ends > 0.5) & (ends < 31.5)).all(axis=-1) & np.isfinite(t_all)  # (B, R) hits inside the cube
    assert inside.sum() > 3000
    passed = inside & (depth > t_all + 1.0)  # (B, R) went through the plate
    assert int(passed.sum()) == 0, f"{int(passed.sum())} rays passed through a thin wall"
    assert (sem[inside] > 0).all()


def test_grazing_rays_along_a_floor_never_go_below_it() -> None:
    scene = AnalyticScene((Box((-1.0, -1.0, -1.0), (33.0, 33.0, 8.3)),), resolution=32, voxel_size=1.0)
    corpus = load_scene(scene.gmdag())
    heights = np.array([0.15, 0.3, 0.6, 1.0, 2.0])  # voxels above the floor (z = 8.3)
    origins = np.stack([np.full(5, 2.0), np.full(5, 16.0), 8.3 + heights], axis=1)  # (5, 3)
    slopes = np.array([0.0, -0.005, -0.02, -0.05, -0.1])
    dirs = np.stack([np.ones(5), np.zeros(5), slopes], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)  # (R, 3)
    depth, _ = _depth(corpus, origins, dirs, max_steps=4000, horizon=1000.0)
    end_z = origins[:, None, 2] + depth * dirs[None, :, 2]  # (B, R) height where each ray stopped
    hit = depth < 1000.0  # (B, R)
    assert (end_z[hit] >= 8.3 - 0.3).all()  # a hit is never more than a fraction of a voxel below the floor
    assert (depth[:, 0] == 1000.0).all()  # level rays above the hit epsilon fly out of the cube
    # A descending ray stops within the hit epsilon (0.1 voxel) above the floor; along a ray of
    # slope s that is 0.1 / s voxels before the exact hit, so the check is on the height.
    run = heights[:, None] / np.maximum(-dirs[None, :, 2], 1e-9)  # (B, R) exact distance to the floor
    lands = (slopes[None, :] < 0) & (origins[:, None, 0] + run * dirs[None, :, 0] < 30.0)  # (B, R)
    assert lands.sum() >= 10 and hit[lands].all()
    assert (end_z[lands] <= 8.3 + 0.1 + 1e-3).all()


def test_origins_inside_solid_return_zero_and_a_hit() -> None:
    scene = AnalyticScene((Box((4.0, 4.0, 4.0), (12.0, 12.0, 12.0)),), resolution=32, voxel_size=0.5)
    corpus = load_scene(scene.gmdag())
    origins = np.array([[8.0, 8.0, 8.0], [5.0, 6.0, 7.0], [4.2, 4.2, 4.2]])  # inside the box, meters
    dirs = random_directions(50, seed=1)  # (R, 3)
    depth, sem = _depth(corpus, origins, dirs)
    assert (depth == 0).all() and (sem == 1).all()  # class 0 (unknown) -> semantic 1


def test_rays_starting_on_a_surface_see_what_they_face() -> None:
    scene = demo_room(32, 8.0)
    corpus = load_scene(scene.gmdag())
    room = scene.solids[0]
    assert isinstance(room, Room)
    floor_z = room.lo[2]
    origin = np.array([[4.0, 2.0, floor_z]])  # exactly on the floor
    up = np.array([[0.0, 0.0, 1.0]])
    down = np.array([[0.0, 0.0, -1.0]])
    d_up, s_up = _depth(corpus, origin, up)
    d_down, s_down = _depth(corpus, origin, down)
    ceiling = room.hi[2] - floor_z
    assert abs(d_up[0, 0] - ceiling) <= scene.voxel_size and s_up[0, 0] > 0
    assert d_down[0, 0] <= 0.25 * scene.voxel_size and s_down[0, 0] > 0


def test_rays_leaving_the_cube_miss_and_outside_origins_enter_it() -> None:
    scene = AnalyticScene((Box((6.0, 6.0, 6.0), (10.0, 10.0, 10.0)),), resolution=16, voxel_size=1.0)
    corpus = load_scene(scene.gmdag())
    origins = np.array([[-20.0, 8.0, 8.0], [8.0, 8.0, 40.0], [1.0, 1.0, 1.0]])  # (3, 3)
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # (4, 3)
    depth, sem = _depth(corpus, origins, dirs, horizon=50.0)
    assert abs(depth[0, 0] - 26.0) < 0.2 and sem[0, 0] > 0  # enters the cube at x=0, hits the box at 6
    assert abs(depth[1, 1] - 30.0) < 0.2 and sem[1, 1] > 0  # enters at z=16, hits the box top at 10
    assert depth[0, 2] == 50.0 and sem[0, 2] == 0  # points away from the cube
    assert depth[2, 2] == 50.0 and depth[2, 3] == 50.0  # leaves the cube: a miss, the horizon
    assert (sem[2, 2:] == 0).all()


def test_a_far_step_across_the_scene_face_is_a_miss_at_that_step() -> None:
    # The origin lies in the far-free cube [0, 16]^3 voxels at a corner of the scene; rays into the
    # corner's octant leave that cube through faces of the scene's cube, so the one far step from the
    # origin sample passes the slab exit t1 and ends the ray as a miss (the kernels test no cell
    # across the exit face). The reference takes the same single step.
    scene = AnalyticScene((Box((28.0, 28.0, 28.0), (36.0, 36.0, 36.0)),), resolution=64, voxel_size=1.0)
    corpus = load_scene(scene.gmdag())
    gen = torch.Generator().manual_seed(3)
    dirs = -(0.1 + torch.rand(64, 3, generator=gen))  # (R, 3) every component negative
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    origins = torch.tensor([[2.0, 3.0, 2.5]])  # (1, 3)
    ids = torch.zeros(1, dtype=torch.int64)
    for tracer in (trace, trace_ref):
        depth = torch.empty(1, 64)  # (1, R)
        sem = torch.empty(1, 64, dtype=torch.int32)  # (1, R)
        steps = torch.empty(1, 64, dtype=torch.int32)  # (1, R)
        tracer(corpus, ids, origins, dirs, out_depth=depth, out_semantic=sem, out_steps=steps, horizon=50.0)
        assert (depth == 50.0).all() and (sem == 0).all()
        assert (steps == 1).all()


def test_rays_along_a_lattice_plane_drifting_out_of_it_keep_going() -> None:
    # Origins exactly on the lattice plane x = 24 voxels, directions with a vanishing x component: an
    # exit time along x is 0 or huge there, and no skip may send the ray backwards or stall it.
    scene = AnalyticScene((Room((1.0, 1.0, 1.0), (15.0, 15.0, 7.0)),), resolution=32, voxel_size=0.5)
    corpus = load_scene(scene.gmdag())
    origins = np.array([[12.0, 10.0, 4.0]])  # (1, 3) voxel (24, 20, 8)
    dirs = np.array(
        [[-1.8e-16, -0.98079, 0.19509], [1.8e-16, -0.98079, 0.19509], [-1e-9, -1.0, 0.0]]
    )  # (3, 3)
    depth, sem = _depth(corpus, origins, dirs, max_steps=64)
    want = 9.0 / -dirs[:, 1]  # (3,) to the wall at y = 1 m
    assert np.all(np.abs(depth[0] - want) < 0.25 * 0.5) and (sem[0] > 0).all()


def test_horizon_and_max_steps_semantics() -> None:
    scene = AnalyticScene((Room((1.0, 1.0, 1.0), (31.0, 31.0, 31.0)),), resolution=32, voxel_size=1.0)
    corpus = load_scene(scene.gmdag())
    origin = np.array([[2.0, 16.0, 16.0]])
    ahead = np.array([[1.0, 0.0, 0.0]])
    near, s_near = _depth(corpus, origin, ahead, horizon=10.0)
    assert near[0, 0] == 10.0 and s_near[0, 0] == 0  # the wall at 29 m lies beyond the horizon
    far, s_far = _depth(corpus, origin, ahead, horizon=100.0)
    assert abs(far[0, 0] - 29.0) < 0.2 and s_far[0, 0] > 0
    short, s_short = _depth(corpus, origin, ahead, max_steps=2)
    assert 0.0 < short[0, 0] < 29.0 and s_short[0, 0] == 0  # out of steps: distance reached so far


def test_out_of_range_scene_id_without_validation_gives_nan() -> None:
    corpus = load_scene(demo_room(16, 4.0).gmdag())
    depth, sem = _depth(corpus, np.full((2, 3), 2.0), random_directions(4), ids=np.array([0, 3]),
                        skip_direction_validation=True)  # fmt: skip
    assert np.isfinite(depth[0]).all() and np.isnan(depth[1]).all() and (sem[1] == 0).all()


@pytest.fixture(scope="module")
def small() -> SceneCorpus:
    return load_scene(demo_room(16, 4.0).gmdag())


def _args(b: int = 2, r: int = 3) -> dict[str, torch.Tensor]:
    dirs = torch.tensor(random_directions(r), dtype=torch.float32)  # (R, 3)
    return {
        "scene_ids": torch.zeros(b, dtype=torch.int64),
        "origins": torch.full((b, 3), 2.0),
        "directions": dirs,
        "out_depth": torch.empty(b, r),
    }


def _call(corpus: SceneCorpus, **over: object) -> None:
    a: dict[str, object] = {**_args(), **over}
    trace(corpus, a.pop("scene_ids"), a.pop("origins"), a.pop("directions"), **a)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("override", "error", "match"),
    [
        ({"origins": torch.full((2, 3), 2.0, dtype=torch.float64)}, TypeError, "origins must be float32"),
        ({"scene_ids": torch.zeros(2, dtype=torch.float32)}, TypeError, "scene_ids must be int32 or int64"),
        ({"origins": torch.full((3, 3), 2.0)}, ValueError, r"origins must have shape \(2, 3\)"),
        ({"directions": torch.zeros(3, 4)}, ValueError, r"directions must have shape \(3, 3\)"),
        ({"directions": torch.zeros(3)}, ValueError, "directions must be"),
        ({"out_depth": torch.empty(2, 4)}, ValueError, r"out_depth must have shape \(2, 3\)"),
        ({"out_depth": torch.empty(3, 2).t()}, ValueError, "out_depth must be contiguous"),
        (
            {"out_semantic": torch.empty(2, 3, dtype=torch.int64)},
            TypeError,
            "out_semantic must be int32 or uint8",
        ),
        ({"yaw": torch.zeros(3)}, ValueError, r"yaw must have shape \(2,\)"),
        ({"scene_ids": torch.tensor([0, 1])}, ValueError, "scene_ids must lie in"),
        ({"scene_ids": torch.tensor([-1, 0])}, ValueError, "scene_ids must lie in"),
        ({"origins": np.zeros((2, 3), np.float32)}, TypeError, "origins must be a torch.Tensor"),
        ({"max_steps": 0}, ValueError, "max_steps"),
        ({"horizon": float("inf")}, ValueError, "horizon"),
        ({"hit_epsilon": -1.0}, ValueError, "hit_epsilon"),
        ({"hit_slope": -0.01}, ValueError, "hit_slope"),
        ({"hit_slope": 1.0}, ValueError, "hit_slope"),
        ({"hit_slope": float("nan")}, ValueError, "hit_slope"),
    ],
)
def test_validation_rejects_bad_arguments(
    small: SceneCorpus, override: dict[str, object], error: type[Exception], match: str
) -> None:
    with pytest.raises(error, match=match):
        _call(small, **override)


@pytest.mark.parametrize(
    "bad", [[0.0, 0.0, 0.0], [float("nan"), 0.0, 1.0], [1.0, 1.0, 0.0], [float("inf"), 0.0, 0.0]]
)
def test_zero_nan_and_unnormalised_directions_are_rejected(small: SceneCorpus, bad: list[float]) -> None:
    dirs = torch.tensor(random_directions(3), dtype=torch.float32)  # (R, 3)
    dirs[1] = torch.tensor(bad)
    with pytest.raises(ValueError, match="unit vectors"):
        _call(small, directions=dirs)
    per_actor = dirs[None].repeat(2, 1, 1).contiguous()  # (B, R, 3)
    with pytest.raises(ValueError, match="unit vectors"):
        _call(small, directions=per_actor)


def test_tensors_on_another_device_are_rejected(small: SceneCorpus) -> None:
    meta = torch.empty(2, 3, device="meta")  # (B, R) on a different device
    with pytest.raises(ValueError, match="is on meta but the scenes are on cpu"):
        _call(small, out_depth=meta)
