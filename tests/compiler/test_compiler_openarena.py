"""Compile a real OpenArena map (openarena-081-maps, GPL-2+): inside seeding, no leak, spawns free,
engines byte-identical."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from navi_compiler.compile import compile_scene
from navi_compiler.gmdag import FLAG_INSIDE_SEEDS, dense_lattice, encode_gmdag
from navi_compiler.ingest import load_scene

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


def test_oa_dm1_compiles_from_its_spawns() -> None:
    scene = load_scene(PK3, map_name="oa_dm1")
    g, stats = compile_scene(scene, resolution=128)
    assert not stats.leaked and g.flags == FLAG_INSIDE_SEEDS and stats.seeds_used == len(scene.seeds)
    assert 0.01 < stats.free_fraction < 0.5  # the arena, not the whole cube, is free
    dense = dense_lattice(g)  # (129, 129, 129)
    idx = np.round((g.spawns - np.array(g.origin)) / g.voxel_size).astype(np.int64)  # (S, 3)
    assert (dense[idx[:, 0], idx[:, 1], idx[:, 2]] > 0).all()  # every spawn point is free
    corners = dense[[0, -1]][:, [0, -1]][:, :, [0, -1]]
    assert (corners < 0).all()  # outside the map is solid
    ref, _ = compile_scene(scene, resolution=64, engine="ref")
    cpp, _ = compile_scene(scene, resolution=64, engine="cpp")
    assert encode_gmdag(ref) == encode_gmdag(cpp)


def test_oa_dm7_is_sealed_by_its_slime_stained_brick_walls() -> None:
    """oa_dm7's fog pit is closed at its foot by world brushes of `gothic_block/blocks17slime`, a solid
    brick texture whose name holds "slime" only glued to "blocks17": the brushes stay solid barriers
    and the fill from the spawns stays inside the map."""
    scene = load_scene(PK3, map_name="oa_dm7")
    tris = scene.vertices[scene.barrier_faces] / 0.0254  # (Fb, 3, 3) map units
    x, y, z = tris[..., 0], tris[..., 1], tris[..., 2]  # (Fb, 3) each
    foot = (
        np.isclose(z, -448.0).all(axis=1)
        & (x >= 320.0 - 1e-6).all(axis=1)
        & np.isclose(x, 352.0).any(axis=1)
        & (y >= -736.0 - 1e-6).all(axis=1)
        & (y <= -608.0 + 1e-6).all(axis=1)
    )  # (Fb,) the underside of the brick brush beside the pit's floor
    assert foot.any()
    for resolution in (64, 128):
        g, stats = compile_scene(scene, resolution=resolution)
        assert not stats.leaked and g.flags == FLAG_INSIDE_SEEDS and stats.seeds_used == len(scene.seeds)
        dense = dense_lattice(g)  # (R+1, R+1, R+1)
        corners = dense[[0, -1]][:, [0, -1]][:, :, [0, -1]]
        assert (corners < 0).all()  # outside the map is solid


def test_oa_dm3_fits_its_cube_to_the_level_not_its_distant_scenery() -> None:
    """oa_dm3's vertices span about 630 m (a hull brush round the level and scenery far outside it) for a
    level under 80 m across. The compile drops what no spawn reaches: at 256³ the voxel is 0.31 m, not
    2.5 m, and the fill from every spawn stays inside; the whole scene at that voxel leaks."""
    scene = load_scene(PK3, map_name="oa_dm3")
    lo, hi = scene.bounds
    assert (hi - lo).max() > 600.0
    g, stats = compile_scene(scene, resolution=256)
    assert stats.detached_parts >= 2 and stats.voxel_size < 0.32
    assert not stats.leaked and g.flags == FLAG_INSIDE_SEEDS and stats.seeds_used == len(scene.seeds)
    dense = dense_lattice(g)  # (257, 257, 257)
    idx = np.round((g.spawns - np.array(g.origin)) / g.voxel_size).astype(np.int64)  # (S, 3)
    assert (dense[idx[:, 0], idx[:, 1], idx[:, 2]] > 0).all()  # every spawn point is free
    _, whole = compile_scene(scene, resolution=256, detached=False)
    assert whole.voxel_size > 2.0 and whole.leaked
