"""engine="torch" (sdf_torch.py): byte-identical files to the NumPy reference on CPU (and on CUDA,
@pytest.mark.gpu), and each torch stage equal to its reference twin."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from navi_compiler.compile import compile_scene
from navi_compiler.dag.build import brick_reduce
from navi_compiler.gmdag import FLAG_INSIDE_SEEDS, FLAG_LEAK_FALLBACK, encode_gmdag
from navi_compiler.scene import Scene
from navi_compiler.sdf.distance import make_triangles, nearest_triangles
from navi_compiler.sdf.farfield import NO_SITE, squared_edt
from navi_compiler.sdf.sign import flood
from navi_compiler.sdf.torch_engine import TorchConfig, brick_min_edt, make_tri, nearest_within
from navi_compiler.sdf.torch_engine import flood as flood_t

CUDA = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is false)"
)

pytestmark = pytest.mark.usefixtures("single_thread")


Mesh = tuple[
    np.ndarray, np.ndarray
]  # ((V, 3) float64 vertices, (F, 3) int64 faces); no trimesh on the GPU box

CUBE_FACES = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ],
    np.int64,
)  # (12, 3) over corners c = x | y << 1 | z << 2


def _scene(meshes: list[Mesh], seeds: list[list[float]], barrier: list[Mesh]) -> Scene:
    verts = [v for v, _ in meshes + barrier]
    offsets = np.cumsum([0] + [len(v) for v in verts])
    faces = [f + offsets[i] for i, (_, f) in enumerate(meshes)]
    bar = [np.zeros((0, 3), np.int64)] + [f + offsets[len(meshes) + i] for i, (_, f) in enumerate(barrier)]
    return Scene(
        name="torch-test",
        vertices=np.concatenate(verts),
        faces=np.concatenate(faces),
        face_class=np.concatenate([np.full(len(f), 1 + i % 2, np.uint8) for i, (_, f) in enumerate(meshes)]),
        class_names=("unknown", "wall", "thing"),
        barrier_faces=np.concatenate(bar),
        seeds=np.array(seeds, np.float64).reshape(-1, 3),
    )


def _rotation(angle: float) -> np.ndarray:
    """(3, 3) rotation by `angle` about the axis (0.3, 1, 0.2) (Rodrigues)."""
    k = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])  # (3,)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])  # (3, 3)
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _box(ext: tuple[float, float, float], centre: tuple[float, float, float], angle: float = 0.0) -> Mesh:
    corners = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.float64) - 0.5  # (8, 3)
    verts = (corners * np.array(ext)) @ _rotation(angle).T + np.array(centre)  # (8, 3)
    return verts, CUBE_FACES.copy()


def _octahedron(radius: float, centre: tuple[float, float, float]) -> Mesh:
    verts = np.concatenate([np.eye(3), -np.eye(3)]) * radius + np.array(centre)  # (6, 3)
    faces = np.array(
        [[0, 1, 2], [1, 3, 2], [3, 4, 2], [4, 0, 2], [1, 0, 5], [3, 1, 5], [4, 3, 5], [0, 4, 5]], np.int64
    )  # (8, 3)
    return verts, faces


def _room(size: float, wall: float, gap: bool) -> list[Mesh]:
    """Six wall slabs; with `gap`, one wall is only a narrow post (the room leaks)."""
    parts = []
    for axis in range(3):
        for side in (-1, 1):
            ext = [size + wall] * 3
            ext[axis] = wall
            if gap and axis == 0 and side == 1:
                ext[1] = size * 0.3
            centre = [0.0, 0.0, 0.0]
            centre[axis] = side * size / 2
            parts.append(_box((ext[0], ext[1], ext[2]), (centre[0], centre[1], centre[2])))
    return parts


SCENES = {
    "room+seed": lambda: _scene(
        [*_room(4.0, 0.3, False), _box((0.6, 0.4, 0.5), (0.3, 0.2, -0.1), 0.7)], [[0.5, 0.5, 0.5]], []
    ),
    "leaky room": lambda: _scene(_room(4.0, 0.3, True), [[0.2, 0.1, 0.3]], []),
    "closed objects": lambda: _scene(
        [_box((1.0, 2.0, 0.7), (0.0, 0.0, 0.0), 0.4), _octahedron(0.6, (1.4, 0.1, 0.05))],
        [],
        [],
    ),
    "thin slab + barrier": lambda: _scene(
        [_box((3.0, 3.0, 0.02), (0.0, 0.0, 0.0), 0.1), _box((0.5, 0.5, 0.5), (0.8, 0.8, 0.6))],
        [[0.1, 0.1, 0.8]],
        [_box((3.6, 3.6, 0.1), (0.0, 0.0, 1.5)), _box((3.6, 3.6, 0.1), (0.0, 0.0, -1.5))],
    ),
}


def _assert_same_file(scene: Scene, resolution: int, device: str) -> None:
    g_ref, s_ref = compile_scene(scene, resolution=resolution, engine="ref")
    g_t, s_t = compile_scene(scene, resolution=resolution, engine="torch", device=device)
    assert encode_gmdag(g_t) == encode_gmdag(g_ref)
    for key in ("seeds_used", "leaked", "wall_points", "free_fraction", "node_count", "brick_count"):
        assert getattr(s_t, key) == getattr(s_ref, key), key


@pytest.mark.parametrize("name", sorted(SCENES))
def test_torch_cpu_file_equals_reference_32(name: str) -> None:
    _assert_same_file(SCENES[name](), 32, "cpu")


def test_torch_cpu_file_equals_reference_64() -> None:
    _assert_same_file(SCENES["room+seed"](), 64, "cpu")


def test_scenes_cover_the_fill_cases() -> None:
    """The parity scenes exercise inside seeding, the leak fallback and outside seeding."""
    flags = {
        name: compile_scene(make(), resolution=32, engine="torch")[0].flags for name, make in SCENES.items()
    }
    assert flags["room+seed"] == FLAG_INSIDE_SEEDS
    assert flags["leaky room"] == FLAG_LEAK_FALLBACK
    assert flags["closed objects"] == 0


@pytest.mark.gpu
@CUDA
@pytest.mark.parametrize("resolution", [32, 64])
def test_torch_cuda_file_equals_reference(resolution: int) -> None:
    for make in SCENES.values():
        _assert_same_file(make(), resolution, "cuda")


def test_nearest_within_equals_reference_with_ties() -> None:
    """Exact float64 distances and nearest indices, duplicated triangles resolving to the lower index,
    near-collinear slivers (whose normals cannot prune) included."""
    rng = np.random.default_rng(3)
    corners = rng.uniform(2.0, 14.0, (40, 3, 3))  # (T, 3, 3) voxels
    corners[:, 1] = corners[:, 0] + rng.uniform(-3, 3, (40, 3))
    corners[:, 2] = corners[:, 0] + rng.uniform(-3, 3, (40, 3))
    slivers = corners[:6].copy()
    slivers[:, 2] = 0.5 * (slivers[:, 0] + slivers[:, 1]) + 1e-9 * np.array([0.0, 0.3, 1.0])  # near-collinear
    corners = np.concatenate([corners, corners[::3], slivers])  # duplicates tie exactly
    ref = nearest_triangles(make_triangles(corners), 16, 5.0)
    for tile in (2, 4):
        got = nearest_within(
            make_tri(corners, torch.device("cpu")), 1, 0, 17, 5.0, TorchConfig(tile=tile, chunk_pairs=4096)
        )
        assert np.array_equal(got.distance.numpy(), ref.distance)
        assert np.array_equal(got.triangle.numpy(), ref.triangle)
    assert not ((ref.triangle >= 40) & (ref.triangle < 54)).any()  # a duplicate never beats its original
    assert (ref.triangle >= 54).any()  # the slivers are nearest somewhere


def test_fill_equals_reference_flood() -> None:
    rng = np.random.default_rng(5)
    for density in (0.2, 0.3, 0.45):
        wall = rng.random((21, 21, 21)) < density  # (n, n, n) bool
        start = np.zeros_like(wall)
        start[10, 10, 10] = True
        start[0, 3, 4] = True
        ref = flood(start, wall)
        got, border = flood_t(torch.from_numpy(start), torch.from_numpy(wall), False)
        assert np.array_equal(got.numpy(), ref)
        assert border == bool(
            ref[0].any()
            | ref[-1].any()
            | ref[:, 0].any()
            | ref[:, -1].any()
            | ref[:, :, 0].any()
            | ref[:, :, -1].any()
        )


def test_brick_min_edt_equals_reference() -> None:
    """The brick minimum of the exact squared EDT, computed at brick resolution."""
    rng = np.random.default_rng(7)
    for density in (0.0, 1e-4, 3e-3):
        sites = rng.random((33, 33, 33)) < density  # (n, n, n) bool
        ref = brick_reduce(squared_edt(sites).astype(np.float32), np.minimum)  # exact below 2^24
        got = brick_min_edt(torch.from_numpy(sites)).numpy()
        if not sites.any():
            assert (got >= NO_SITE).all()
        else:
            assert np.array_equal(got, ref.astype(np.int64))


def test_bench_cli_reports_warmup(tmp_path: Path) -> None:
    from navi.cli import build_app

    src = tmp_path / "thing.obj"
    verts, faces = _box((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    src.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in verts)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)
    )
    res = CliRunner().invoke(
        build_app(), ["bench", "compile", str(src), "--resolution", "16", "--engine", "torch"]
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["engine"] == "torch" and out["resolution"] == 16 and out["warmup_seconds"] > 0
    bad = CliRunner().invoke(build_app(), ["bench", "compile", str(src), "--device", "cuda"])
    assert bad.exit_code == 2 and "--engine torch" in bad.output


PK3 = Path(
    os.environ.get(
        "NAVI_OPENARENA_PK3", Path(__file__).resolve().parents[2] / "artifacts/data/openarena/pak1-maps.pk3"
    )
)


@pytest.mark.gpu
@pytest.mark.data
@CUDA
@pytest.mark.skipif(
    not PK3.is_file(),
    reason=f"OpenArena maps pk3 not found at {PK3} (run tests/data/fetch_openarena.sh or set NAVI_OPENARENA_PK3)",
)
def test_torch_cuda_openarena_equals_cpp() -> None:
    """A real map (oa_dm1: spawns, barrier brushes, Bezier patches) at 256^3: the same file as the C++ core."""
    from navi_compiler.ingest import load_scene

    scene = load_scene(PK3, map_name="oa_dm1")
    g_cpp, s_cpp = compile_scene(scene, resolution=256, engine="cpp")
    g_t, s_t = compile_scene(scene, resolution=256, engine="torch", device="cuda")
    assert encode_gmdag(g_t) == encode_gmdag(g_cpp)
    assert s_t.seeds_used == s_cpp.seeds_used == len(scene.seeds) and not s_t.leaked
