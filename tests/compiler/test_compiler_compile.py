"""The compiler end to end: both engines byte-identical, deterministic, accurate, thin walls blocked,
leaks detected, classes assigned."""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
import pytest
import torch
import trimesh

from navi_compiler.compile import compile_scene
from navi_compiler.gmdag import (
    FLAG_INSIDE_SEEDS,
    FLAG_LEAK_FALLBACK,
    PAYLOAD_MASK,
    TAG_FAR_FREE,
    Gmdag,
    dense_lattice,
    encode_gmdag,
    leaf_cubes,
)
from navi_compiler.scene import Scene
from navi_compiler.sdf.grid import place, round_resolution


def _mesh_scene(
    meshes: list[trimesh.Trimesh],
    classes: list[int],
    seeds: list[list[float]] | None = None,
    barrier: list[trimesh.Trimesh] | None = None,
) -> Scene:
    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    face_class: list[np.ndarray] = []
    offset = 0
    for m, c in zip(meshes, classes, strict=True):
        verts.append(np.asarray(m.vertices, np.float64))
        faces.append(np.asarray(m.faces, np.int64) + offset)
        face_class.append(np.full(len(m.faces), c, np.uint8))
        offset += len(m.vertices)
    bar_faces: list[np.ndarray] = [np.zeros((0, 3), np.int64)]
    for m in barrier or []:
        verts.append(np.asarray(m.vertices, np.float64))
        bar_faces.append(np.asarray(m.faces, np.int64) + offset)
        offset += len(m.vertices)
    return Scene(
        name="test",
        vertices=np.concatenate(verts),
        faces=np.concatenate(faces),
        face_class=np.concatenate(face_class),
        class_names=("unknown", "solid", "slab", "room"),
        barrier_faces=np.concatenate(bar_faces),
        seeds=np.array(seeds if seeds else np.zeros((0, 3)), np.float64).reshape(-1, 3),
    )


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents, trimesh.transformations.translation_matrix(centre))


def _room(size: float, wall: float, hole: bool) -> list[trimesh.Trimesh]:
    """A hollow cube room from six wall slabs (optionally with a doorway through one wall)."""
    half = size / 2
    parts = []
    for axis in range(3):
        for side in (-1, 1):
            ext = [size + wall] * 3
            ext[axis] = wall
            centre = [0.0, 0.0, 0.0]
            centre[axis] = side * half
            if hole and axis == 0 and side == 1:
                ext[1] = size * 0.3  # a narrow post instead of a full wall: the gaps beside it leak
            parts.append(_box((ext[0], ext[1], ext[2]), (centre[0], centre[1], centre[2])))
    return parts


def _lattice_points(g: Gmdag) -> np.ndarray:
    x = np.arange(g.resolution + 1, dtype=np.float64)  # (R+1,)
    gx, gy, gz = np.meshgrid(x, x, x, indexing="ij")
    return np.stack([gx, gy, gz], axis=-1) * g.voxel_size + np.array(g.origin)  # (R+1, R+1, R+1, 3) meters


def _box_sdf(p: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p - centre) - half  # (..., 3)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _scenes() -> dict[str, Scene]:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.8)
    slab = _box((2.0, 1.5, 0.03), (0.0, 0.0, 1.2))
    room = _room(3.0, 0.2, hole=False)
    leaky = _room(3.0, 0.2, hole=True)
    return {
        "outside": _mesh_scene([sphere, slab], [1, 2]),
        "inside": _mesh_scene([*room, sphere], [3] * 6 + [1], seeds=[[0.9, 0.9, 0.9]]),
        "leak": _mesh_scene([*leaky, sphere], [3] * 6 + [1], seeds=[[0.9, 0.9, 0.9]]),
        "barrier": _mesh_scene(
            [sphere],
            [1],
            seeds=[[0.0, 0.0, 1.3]],
            barrier=[_box((3.0, 3.0, 0.1), (0.0, 0.0, -1.2)), _box((3.0, 3.0, 0.1), (0.0, 0.0, 1.6))],
        ),
    }


@pytest.mark.parametrize("name", ["outside", "inside", "leak", "barrier"])
def test_engines_are_byte_identical(name: str) -> None:
    scene = _scenes()[name]
    ref, ref_stats = compile_scene(scene, resolution=32, engine="ref")
    cpp, cpp_stats = compile_scene(scene, resolution=32, engine="cpp", threads=2)
    assert encode_gmdag(ref) == encode_gmdag(cpp)
    assert (ref_stats.wall_points, ref_stats.seeds_used, ref_stats.leaked) == (
        cpp_stats.wall_points,
        cpp_stats.seeds_used,
        cpp_stats.leaked,
    )


def test_engines_agree_at_64_and_compiles_repeat_exactly() -> None:
    scene = _scenes()["inside"]
    ref = encode_gmdag(compile_scene(scene, resolution=64, engine="ref")[0])
    one = encode_gmdag(compile_scene(scene, resolution=64, engine="cpp", threads=1)[0])
    two = encode_gmdag(compile_scene(scene, resolution=64, engine="cpp", threads=2)[0])
    again = encode_gmdag(compile_scene(scene, resolution=64, engine="cpp", threads=2)[0])
    assert ref == one == two == again


def test_inside_seeds_and_leaks_set_flags_and_never_invert(caplog: pytest.LogCaptureFixture) -> None:
    scenes = _scenes()
    inside, _ = compile_scene(scenes["inside"], resolution=64)
    assert inside.flags == FLAG_INSIDE_SEEDS
    dense = dense_lattice(inside)
    pts = _lattice_points(inside)
    r = np.linalg.norm(pts, axis=-1)
    in_room = (np.abs(pts).max(axis=-1) < 1.3) & (r > 1.0)  # free air inside the room
    outside = np.abs(pts).max(axis=-1) > 1.8  # beyond the walls: unreachable from the seed
    assert (dense[in_room] > 0).all()
    assert (dense[outside] < 0).all()
    with caplog.at_level(logging.WARNING):
        leak, stats = compile_scene(scenes["leak"], resolution=64)
    assert stats.leaked and leak.flags == FLAG_LEAK_FALLBACK
    assert "leaks" in caplog.text
    dense = dense_lattice(leak)
    assert (dense[in_room] > 0).all() and (dense[outside] > 0).all()  # outside seeding: all air is free


def test_accuracy_against_an_exact_box() -> None:
    centre, half = np.array([0.1, -0.2, 0.05]), np.array([0.9, 0.6, 0.45])
    scene = _mesh_scene([_box(tuple(2 * half), tuple(centre))], [1])
    g, _ = compile_scene(scene, resolution=64, min_band_m=0.0)  # the 4-voxel band's quantisation
    dense = dense_lattice(g).astype(np.float64)  # (65, 65, 65) voxels
    exact = _box_sdf(_lattice_points(g), centre, half) / g.voxel_size  # (65, 65, 65) voxels, signed
    band = np.abs(exact) <= 4.0
    err = np.abs(dense[band]) - np.abs(exact[band])
    assert np.quantile(np.abs(err), 0.99) <= 0.1
    assert err.max() <= 0.05
    assert (np.abs(dense) <= np.abs(exact) + 1e-4).all()  # far samples and far codes never over-estimate
    clear = np.abs(exact) > 0.5
    assert (np.sign(dense[clear]) == np.sign(exact[clear])).all()
    # Far codes promise their whole cube: check random points of every far cube against the exact field.
    words, depth, corner = leaf_cubes(g)
    rng = np.random.default_rng(0)
    for w, d, c in zip(words, depth, corner, strict=True):
        if int(w) >> 30 < TAG_FAR_FREE:
            continue
        side = g.resolution >> int(d)
        probe = (c + rng.uniform(0, side, (64, 3))) * g.voxel_size + np.array(g.origin)  # (64, 3) meters
        truth = _box_sdf(probe, centre, half) / g.voxel_size  # (64,) voxels
        bound = (int(w) & PAYLOAD_MASK) / 16
        assert (np.abs(truth) >= bound).all()
        assert (np.sign(truth) == (1 if int(w) >> 30 == TAG_FAR_FREE else -1)).all()


@pytest.mark.parametrize("thickness", [0.25, 0.5, 1.0, 2.0])
def test_thin_walls_always_show_a_sign_change(thickness: float) -> None:
    # A free-standing slab, free air on both sides; resolution 32 over ~3.2 m -> 0.1 m voxels.
    rng = np.random.default_rng(int(thickness * 100))
    voxel = 3.2 / 30
    z0 = 0.3 + rng.uniform(0, voxel)
    slab = _box((2.0, 2.0, thickness * voxel), (0.0, 0.0, z0))
    anchor = _box((0.2, 0.2, 0.2), (1.4, 1.4, -1.4))  # stretches the scene to a known size
    g, _ = compile_scene(_mesh_scene([slab, anchor], [2, 1]), resolution=32)
    dense = dense_lattice(g)  # (33, 33, 33)
    pts = _lattice_points(g)
    over = (np.abs(pts[..., 0]) < 0.95) & (
        np.abs(pts[..., 1]) < 0.95
    )  # (33, 33, 33) columns through the slab
    columns = np.where(over, dense, np.inf).min(axis=2)  # (33, 33) min along z
    inside_cols = over[..., 0]
    assert (
        columns[inside_cols] <= 0
    ).all()  # every lattice line through the slab meets a non-positive sample


def test_brick_classes_follow_the_nearest_surface() -> None:
    a = _box((0.6, 0.6, 0.6), (-0.8, 0.0, 0.0))
    b = _box((0.6, 0.6, 0.6), (0.8, 0.0, 0.0))
    # the 4-voxel band: every brick is then within the 12-voxel class reach of a surface
    g, _ = compile_scene(_mesh_scene([a, b], [1, 2]), resolution=64, min_band_m=0.0)
    words, _, corner = leaf_cubes(g)
    is_brick = (words >> 30) == 1
    centre_x = (corner[is_brick, 0] + 4) * g.voxel_size + g.origin[0]
    cls = g.brick_class[words[is_brick] & PAYLOAD_MASK]
    assert set(cls[centre_x < -0.3].tolist()) == {1}
    assert set(cls[centre_x > 0.3].tolist()) == {2}
    assert g.class_names[1] == "solid"


def test_placement_centres_the_scene_in_a_power_of_two_cube() -> None:
    assert [round_resolution(r) for r in (1, 8, 9, 40, 64, 500)] == [8, 8, 16, 64, 64, 512]
    lo, hi = np.array([-1.0, 2.0, 0.0]), np.array([3.0, 3.0, 1.0])
    p = place(lo, hi, 40, padding=2)
    assert p.resolution == 64 and p.voxel_size == pytest.approx(4.0 / 60)
    side = p.resolution * p.voxel_size
    assert np.allclose(np.array(p.origin) + side / 2, (lo + hi) / 2)
    with pytest.raises(ValueError, match="no extent"):
        place(lo, lo, 32, padding=2)


@pytest.mark.parametrize("engine", ["ref", "cpp"])
def test_a_barrier_with_free_space_on_both_sides_is_seen_by_the_rays(engine: Literal["ref", "cpp"]) -> None:
    """A barrier pane inside a closed room, open above so the fill reaches both of its sides (a sky pane
    between two areas): the drone cannot pass it, so the field must cross zero there and a ray toward
    it stops at the pane, as it does at a drawn thin wall."""
    from navi_env.tracer.scene import load_scene
    from navi_env.tracer.trace import sample_distance, trace

    room = _room(4.0, 0.2, hole=False)
    # an undrawn pane at x = 0.5 from the floor to z = 0.8: 1.2 m of free air above it joins both sides
    pane = trimesh.Trimesh(
        vertices=[[0.5, -2.0, -2.0], [0.5, 2.0, -2.0], [0.5, 2.0, 0.8], [0.5, -2.0, 0.8]],
        faces=[[0, 1, 2], [0, 2, 3]],
    )
    scene = _mesh_scene(room, [3] * 6, seeds=[[-1.0, 0.0, 0.0], [1.2, 0.0, 0.0]], barrier=[pane])
    g, stats = compile_scene(scene, resolution=64, engine=engine)
    assert not stats.leaked
    corpus = load_scene(g)
    # rays along +x at heights below the pane's top, from 1.0 m in front of it
    z = torch.linspace(-1.5, 0.5, 9)  # (B,)
    origins = torch.stack([torch.full_like(z, -0.5), torch.zeros_like(z), z], 1).contiguous()  # (B, 3)
    ids = torch.zeros(len(z), dtype=torch.int32)  # (B,)
    depth = torch.empty(len(z), 1)  # (B, 1)
    direction = torch.tensor([[1.0, 0.0, 0.0]])  # (1, 3)
    trace(corpus, ids, origins, direction, out_depth=depth, horizon=20.0)
    assert torch.allclose(depth[:, 0], torch.ones(len(z)), atol=1.5 * g.voxel_size), depth[:, 0]
    # and the field itself crosses zero through the pane (it read a positive ridge before)
    line = torch.stack([torch.linspace(0.3, 0.7, 41), torch.zeros(41), torch.full((41,), -0.5)], 1)  # (41, 3)
    field = sample_distance(corpus, torch.zeros(41, dtype=torch.int32), line.contiguous())  # (41,)
    assert float(field.min()) < 0.0, field
    # above the pane the air is open: a ray at z = 1.2 reaches the far wall at x = 1.9
    high = torch.empty(1, 1)
    trace(corpus, ids[:1], torch.tensor([[-0.5, 0.0, 1.2]]), direction, out_depth=high, horizon=20.0)
    assert abs(float(high) - 2.4) < 1.5 * g.voxel_size, float(high)
