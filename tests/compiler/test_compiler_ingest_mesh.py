"""Mesh ingestion through trimesh: world-space flattening, units, repair, and the scene sidecar."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from navi_compiler.ingest import IngestError, load_scene, sidecar_path
from navi_compiler.ingest.procedural import generate_scene, write_scene_mesh


def _unit_box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 1.0, 1.0))


def test_scene_graph_transforms_are_baked_into_world_space(tmp_path: Path) -> None:
    graph = trimesh.Scene()
    graph.add_geometry(
        _unit_box(), node_name="a", transform=trimesh.transformations.translation_matrix((10, 0, 0))
    )
    scaled = trimesh.transformations.scale_matrix(4.0)
    scaled[:3, 3] = (0.0, 0.0, 20.0)
    graph.add_geometry(_unit_box(), node_name="b", transform=scaled)
    path = tmp_path / "graph.glb"
    graph.export(path)
    scene = load_scene(path)
    assert len(scene.faces) == 24
    lo, hi = scene.bounds
    np.testing.assert_allclose(lo, [-2.0, -2.0, -0.5], atol=1e-6)
    np.testing.assert_allclose(hi, [10.5, 2.0, 22.0], atol=1e-6)
    assert scene.class_names == ("unknown",) and (scene.face_class == 0).all() and len(scene.seeds) == 0


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb"])
def test_every_mesh_format_loads_with_its_scale(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"box{suffix}"
    _unit_box().export(path)
    meters = load_scene(path)
    centimeters = load_scene(path, scale=0.01, seeds=[(0.0, 0.0, 0.0)])
    np.testing.assert_allclose(centimeters.vertices, meters.vertices * 0.01)
    lo, hi = meters.bounds
    np.testing.assert_allclose(hi - lo, [1.0, 1.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(centimeters.seeds, [[0.0, 0.0, 0.0]])


def test_repair_merges_vertices_and_fills_holes(tmp_path: Path) -> None:
    box = _unit_box()
    open_box = trimesh.Trimesh(
        box.vertices[box.faces].reshape(-1, 3), np.arange(30).reshape(10, 3), process=False
    )
    path = tmp_path / "open.obj"
    open_box.export(path)
    raw = load_scene(path)
    fixed = load_scene(path, repair=True)
    assert not trimesh.Trimesh(raw.vertices, raw.faces, process=False).is_watertight
    repaired = trimesh.Trimesh(fixed.vertices, fixed.faces, process=False)
    assert len(fixed.vertices) == 8 and len(fixed.faces) == 12 and repaired.is_watertight
    assert repaired.volume == pytest.approx(1.0)  # normals point outward after the repair


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_written_scenes_load_back_with_classes_seeds_and_barriers(tmp_path: Path, suffix: str) -> None:
    original = generate_scene("forest", 3)  # open top: has barrier faces
    path = write_scene_mesh(original, tmp_path / f"forest{suffix}")
    assert sidecar_path(path).is_file()
    loaded = load_scene(path)
    np.testing.assert_allclose(loaded.vertices[loaded.faces], original.vertices[original.faces], atol=1e-6)
    np.testing.assert_array_equal(loaded.face_class, original.face_class)
    assert loaded.class_names == original.class_names
    np.testing.assert_allclose(loaded.seeds, original.seeds, atol=1e-6)
    np.testing.assert_allclose(
        loaded.vertices[loaded.barrier_faces], original.vertices[original.barrier_faces], atol=1e-6
    )
    doubled = load_scene(path, scale=2.0)
    np.testing.assert_allclose(doubled.seeds, 2.0 * loaded.seeds)


def test_repair_keeps_the_classes_of_surviving_faces(tmp_path: Path) -> None:
    original = generate_scene("maze", 1)
    path = write_scene_mesh(original, tmp_path / "maze.obj")
    repaired = load_scene(path, repair=True)
    kept = repaired.face_class != 0  # faces added by hole filling are "unknown"
    assert kept.sum() == len(original.faces)  # nothing degenerate or duplicated was dropped
    before = {
        tuple(c): k
        for c, k in zip(
            np.round(original.vertices[original.faces].mean(axis=1), 4), original.face_class, strict=True
        )
    }
    after = np.round(repaired.vertices[repaired.faces[kept]].mean(axis=1), 4)
    assert [before[tuple(c)] for c in after] == repaired.face_class[kept].tolist()


def test_sidecar_problems_raise_ingest_errors(tmp_path: Path) -> None:
    path = write_scene_mesh(generate_scene("rooms", 0), tmp_path / "rooms.obj")
    side = sidecar_path(path)
    payload = json.loads(side.read_text())
    payload["faces"] += 1
    payload["face_class_runs"][0][1] += 1
    side.write_text(json.dumps(payload))
    with pytest.raises(IngestError, match="describes"):
        load_scene(path)
    side.write_text("{not json")
    with pytest.raises(IngestError, match="sidecar"):
        load_scene(path)
    payload["format"] = "something-else"
    side.write_text(json.dumps(payload))
    with pytest.raises(IngestError, match="not a 'navi-scene' sidecar"):
        load_scene(path)


def test_sidecar_declares_moving_obstacles(tmp_path: Path) -> None:
    from navi_compiler.ingest.sidecar import read_sidecar, write_sidecar

    path = write_scene_mesh(generate_scene("hall", 0), tmp_path / "hall.obj")
    side = sidecar_path(path)
    plain = read_sidecar(side)
    assert plain.obstacles == {} and "obstacles" not in json.loads(side.read_text())
    write_sidecar(path, dataclasses.replace(plain, obstacles={"count": 5.0, "speed_max": 2.5}))
    assert read_sidecar(side).obstacles == {"count": 5.0, "speed_max": 2.5}
    payload = json.loads(side.read_text())
    for bad in ({"count": "many"}, {"warp_speed": 9.0}, {"count": True}, ["count", 3]):
        payload["obstacles"] = bad
        side.write_text(json.dumps(payload))
        with pytest.raises(IngestError, match="obstacles"):
            read_sidecar(side)


def test_unreadable_or_empty_meshes_raise_ingest_errors(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(b"glTF\x02\x00\x00\x00 nonsense")
    with pytest.raises(IngestError, match="cannot read mesh"):
        load_scene(garbage)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(IngestError):
        load_scene(empty)
    with pytest.raises(IngestError, match="not found"):
        load_scene(tmp_path / "absent.obj")
    with pytest.raises(IngestError, match="map name"):
        load_scene(empty, map_name="oa_dm1")
