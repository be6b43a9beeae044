"""Real Quake 3 maps from OpenArena (openarena-081-maps, GPL-2+): ingestion makes physical sense."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from navi_compiler.ingest import bsp as q3
from navi_compiler.ingest import list_pk3_maps, load_scene

PK3 = Path(
    os.environ.get(
        "NAVI_OPENARENA_PK3", Path(__file__).resolve().parents[2] / "artifacts/data/openarena/pak1-maps.pk3"
    )
)
pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(
        not PK3.is_file(),
        reason=f"OpenArena maps pk3 not found at {PK3} (run tests/data/fetch_openarena.sh or set NAVI_OPENARENA_PK3)",
    ),
]
MAP = "oa_dm5"  # small, with Bézier patches and a sky


@pytest.fixture(scope="module")
def raw() -> q3.BspData:
    with zipfile.ZipFile(PK3) as z:
        return q3.parse_bsp(z.read(f"maps/{MAP}.bsp"))


def _face_centroids(data: q3.BspData, face_ids: np.ndarray, scale: float) -> set[tuple[float, ...]]:
    """Centroids (rounded, meters) of the triangles of polygon/mesh faces, from the raw lumps."""
    tris, _ = q3.face_triangles(data, face_ids)
    centre = data.vertices["position"].astype(np.float64)[tris].mean(axis=1) * scale
    return {tuple(c) for c in np.round(centre, 4)}


def test_the_archive_lists_its_maps() -> None:
    maps = list_pk3_maps(PK3)
    assert len(maps) >= 40 and "oa_dm1" in maps and MAP in maps


def test_map_has_a_plausible_size_and_spawns_inside(raw: q3.BspData) -> None:
    scene = load_scene(PK3, map_name=MAP)
    assert 20_000 <= len(scene.faces) <= 500_000
    lo, hi = scene.bounds
    size = hi - lo
    assert 10.0 <= size.max() <= 300.0 and size.min() >= 3.0, size
    assert len(scene.seeds) >= 4
    assert ((scene.seeds > lo) & (scene.seeds < hi)).all()
    spawns = q3.spawn_origins(q3.parse_entities(raw.entities))
    np.testing.assert_allclose(scene.seeds[:, :2], spawns[:, :2] * 0.0254)  # every spawn kept, XY unchanged
    assert len(scene.barrier_faces) > 0


def test_no_sky_or_trigger_surface_is_drawn_and_sky_bounds_the_fill(raw: q3.BspData) -> None:
    scene = load_scene(PK3, map_name=MAP)
    names = [n.decode("latin-1").lower() for n in raw.shaders["name"]]
    sky_shader = np.array(
        [("sky" in n) or bool(f & q3.SURF_SKY) for n, f in zip(names, raw.shaders["flags"], strict=True)]
    )
    hidden_shader = np.array(
        [
            ("trigger" in n) or ("clip" in n) or bool(c & q3.CONTENTS_TRIGGER)
            for n, c in zip(names, raw.shaders["contents"], strict=True)
        ]
    )
    flat = (raw.faces["type"] == q3.FACE_POLYGON) | (raw.faces["type"] == q3.FACE_MESH)
    sky_faces = np.flatnonzero(flat & sky_shader[raw.faces["shader"]])
    hidden_faces = np.flatnonzero(flat & hidden_shader[raw.faces["shader"]])
    assert len(sky_faces) > 0
    drawn = {tuple(c) for c in np.round(scene.vertices[scene.faces].mean(axis=1), 4)}
    barrier = {tuple(c) for c in np.round(scene.vertices[scene.barrier_faces].mean(axis=1), 4)}
    sky = _face_centroids(raw, sky_faces, 0.0254)
    assert not sky & drawn
    assert sky <= barrier
    assert not _face_centroids(raw, hidden_faces, 0.0254) & drawn


def test_patches_are_tessellated_and_classes_are_meaningful() -> None:
    scene = load_scene(PK3, map_name=MAP)
    counts = np.bincount(scene.face_class, minlength=len(scene.class_names))
    by_name = dict(zip(scene.class_names, counts, strict=True))
    level = q3.BspOptions().patch_level
    assert by_name["patch"] > 0 and by_name["patch"] % (2 * level * level) == 0
    assert by_name["floor"] > 0 and by_name["wall"] > 0 and by_name["ceiling"] > 0
    assert by_name["unknown"] == 0


def test_loading_is_deterministic() -> None:
    a, b = load_scene(f"{PK3}:maps/{MAP}.bsp"), load_scene(PK3, map_name=MAP)
    for name in ("vertices", "faces", "face_class", "barrier_faces", "seeds"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_real_brushes_match_the_clipping_reference(raw: q3.BspData) -> None:
    world = raw.models[0]
    brushes = raw.brushes[int(world["brush"]) : int(world["brush"]) + 300]
    fast = q3.brush_faces(raw.planes, brushes, raw.brushsides, 1e5)
    ref = q3.brush_faces_ref(raw.planes, brushes, raw.brushsides, 1e5)

    def areas(faces: q3.BrushFaces) -> dict[int, float]:
        out = {}
        for side, poly in zip(
            faces.side, np.split(faces.vertices, np.cumsum(faces.counts)[:-1]), strict=True
        ):
            out[int(side)] = 0.5 * float(
                np.linalg.norm(np.cross(poly[1:-1] - poly[0], poly[2:] - poly[0]).sum(axis=0))
            )
        return out

    a, b = areas(fast), areas(ref)
    total = sum(b.values())
    difference = sum(abs(a.get(k, 0.0) - b.get(k, 0.0)) for k in set(a) | set(b))
    assert total > 0 and difference / total < 1e-5
