"""Detached parts: scenery no seed reaches is dropped before the compile, so the cube fits the level;
a level that does not close without it is compiled whole."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
import trimesh

from navi_compiler.compile import compile_scene
from navi_compiler.gmdag import encode_gmdag
from navi_compiler.ingest.detached import drop_detached, kept_parts, part_of_triangles
from navi_compiler.scene import Scene

SEED = [[2.0, 3.0, 1.0]]


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents, trimesh.transformations.translation_matrix(centre))


def _room(size: float = 20.0, wall: float = 0.5, open_side: bool = False) -> list[trimesh.Trimesh]:
    """A hollow cube room centred on the origin, from six wall slabs; open_side leaves out the +x wall."""
    walls = []
    for axis in range(3):
        for side in (-1, 1):
            if open_side and axis == 0 and side == 1:
                continue
            ext = [size + wall] * 3
            ext[axis] = wall
            centre = [0.0, 0.0, 0.0]
            centre[axis] = side * size / 2
            walls.append(_box((ext[0], ext[1], ext[2]), (centre[0], centre[1], centre[2])))
    return walls


def _hull(size: float) -> list[trimesh.Trimesh]:
    """Six thin slabs closing a cube of `size` round the origin (one brush round everything)."""
    return _room(size, 0.5)


def _scene(
    drawn: list[trimesh.Trimesh],
    barrier: list[trimesh.Trimesh] | None = None,
    seeds: list[list[float]] | None = None,
) -> Scene:
    """Drawn and barrier meshes and seeds (default: one seed inside the room) as one Scene."""
    seeds = SEED if seeds is None else seeds
    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    bar: list[np.ndarray] = [np.zeros((0, 3), np.int64)]
    offset = 0
    for m in drawn:
        verts.append(np.asarray(m.vertices, np.float64))
        faces.append(np.asarray(m.faces, np.int64) + offset)
        offset += len(m.vertices)
    for m in barrier or []:
        verts.append(np.asarray(m.vertices, np.float64))
        bar.append(np.asarray(m.faces, np.int64) + offset)
        offset += len(m.vertices)
    f = np.concatenate(faces)
    return Scene(
        name="detached",
        vertices=np.concatenate(verts),
        faces=f,
        face_class=np.zeros(len(f), np.uint8),
        barrier_faces=np.concatenate(bar),
        seeds=np.array(seeds, np.float64).reshape(-1, 3),
    )


def test_far_scenery_is_dropped_and_the_file_is_the_level_alone() -> None:
    """A closed room with the seed and a closed box 200 m away: the box is dropped, and the compiled file
    is byte for byte the room compiled on its own (the same cube, the same field)."""
    room = _room()
    scene = _scene([*room, _box((6.0, 6.0, 6.0), (200.0, 0.0, 0.0))])
    alone = _scene(room)
    g, stats = compile_scene(scene, resolution=64)
    g_alone, stats_alone = compile_scene(alone, resolution=64)
    assert (stats.detached_parts, stats.detached_triangles) == (1, 12)
    assert stats.voxel_size == stats_alone.voxel_size < 0.4  # 20.5 m room in 64 cells, not 207 m
    assert not stats.leaked and stats.seeds_used == 1
    assert encode_gmdag(g) == encode_gmdag(g_alone)
    whole, whole_stats = compile_scene(scene, resolution=64, detached=False)
    assert whole_stats.detached_parts == 0 and whole_stats.voxel_size > 3.0
    assert encode_gmdag(whole) != encode_gmdag(g)


def test_a_hull_round_everything_is_dropped_with_what_lies_outside_the_level() -> None:
    """A barrier hull 400 m across round the room and the far box holds the seed in its box but also holds
    the room's box: it is a shell, not the level, and goes with the far box."""
    scene = _scene([*_room(), _box((6.0, 6.0, 6.0), (150.0, 20.0, 0.0))], barrier=_hull(400.0))
    out, dropped = drop_detached(scene)
    assert dropped is not None and dropped.parts == 2
    assert dropped.faces == 12 and dropped.barrier_faces == 6 * 12
    lo, hi = out.bounds
    np.testing.assert_allclose(lo, [-10.25] * 3)
    np.testing.assert_allclose(hi, [10.25] * 3)
    _, stats = compile_scene(scene, resolution=64)
    assert stats.detached_parts == 2 and not stats.leaked


def test_geometry_inside_the_level_stays_however_far_from_its_walls() -> None:
    """A pillar 60 m from every wall of a 140 m hall is its own part, but it lies in the hall's box: kept."""
    scene = _scene([*_room(140.0, 1.0), _box((2.0, 2.0, 2.0), (5.0, 5.0, 5.0))])
    tri = np.concatenate([scene.faces, scene.barrier_faces])
    assert len(np.unique(part_of_triangles(scene.vertices, tri))) == 2
    out, dropped = drop_detached(scene)
    assert dropped is None and out is scene


def test_a_level_that_leaks_without_the_dropped_part_is_compiled_whole(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The room's +x side is open and only a far hull closes it: without the hull the fill reaches the
    smaller cube's border, so the compile falls back to the whole scene (the same bytes as without the
    rule), and reports nothing dropped."""
    scene = _scene(_room(open_side=True), barrier=_hull(400.0))
    _, dropped = drop_detached(scene)
    assert dropped is not None and dropped.parts == 1
    with caplog.at_level(logging.INFO, logger="navi_compiler.compile"):
        g, stats = compile_scene(scene, resolution=64)
    assert "without its detached parts the fill leaks" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]  # the scene itself does not leak
    g_whole, stats_whole = compile_scene(scene, resolution=64, detached=False)
    assert stats.detached_parts == 0 and not stats.leaked and not stats_whole.leaked
    assert encode_gmdag(g) == encode_gmdag(g_whole)


def test_without_seeds_or_with_a_seed_outside_the_level_nothing_is_dropped() -> None:
    room = [*_room(), _box((6.0, 6.0, 6.0), (200.0, 0.0, 0.0))]
    assert drop_detached(_scene(room, seeds=[]))[1] is None
    # a seed in the far box's box too: that box holds a seed, so it is a level of its own
    assert drop_detached(_scene(room, seeds=[SEED[0], [200.0, 0.0, 0.0]]))[1] is None
    # a seed in no part's box: nothing to anchor the level, so everything stays
    assert drop_detached(_scene(room, seeds=[[100.0, 0.0, 0.0]]))[1] is None


def test_kept_parts_join_what_meets_the_level_and_stop_at_shells() -> None:
    lo = np.array([[0, 0, 0], [9, 0, 0], [18, 0, 0], [-100, -100, -100], [50, 50, 50]], np.float64)  # (5, 3)
    hi = np.array([[10, 10, 10], [19, 10, 10], [30, 10, 10], [100, 100, 100], [60, 60, 60]], np.float64)
    keep = kept_parts(lo, hi, np.array([[1.0, 1.0, 1.0]]))
    # 0 holds the seed; 1 meets it, then 2 meets the grown box; 3 is a shell round them; 4 lies apart
    assert keep.tolist() == [True, True, True, False, False]


def test_a_triangle_spanning_two_clusters_joins_them() -> None:
    """Parts follow triangles as well as cells: one long triangle ties two far clusters into one part."""
    a, b = _box((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), _box((1.0, 1.0, 1.0), (100.0, 0.0, 0.0))
    scene = _scene([a, b])
    tri = np.concatenate([scene.faces, scene.barrier_faces])
    assert len(np.unique(part_of_triangles(scene.vertices, tri))) == 2
    v = np.concatenate([scene.vertices, [[0.4, 0.4, 0.4], [99.6, 0.4, 0.4], [50.0, 0.5, 0.4]]])  # (V + 3, 3)
    joined = dataclasses.replace(
        scene,
        vertices=v,
        faces=np.concatenate([scene.faces, [[len(v) - 3, len(v) - 2, len(v) - 1]]]),
        face_class=np.zeros(len(scene.faces) + 1, np.uint8),
    )
    tri = np.concatenate([joined.faces, joined.barrier_faces])
    assert len(np.unique(part_of_triangles(joined.vertices, tri))) == 1
