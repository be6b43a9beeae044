"""`navi compile`, `navi check` and `navi bench compile` through the root command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from navi.cli import build_app
from navi_compiler.gmdag import FLAG_LEAK_FALLBACK, GmdagError, read_gmdag

runner = CliRunner()


def _mesh() -> trimesh.Trimesh:
    """A unit box at the origin and a 0.3 m sphere beside it, at x = 1.2."""
    parts = [
        trimesh.creation.box((1.0, 1.0, 1.0)),
        trimesh.creation.icosphere(radius=0.3).apply_translation((1.2, 0, 0)),
    ]
    mesh = trimesh.util.concatenate(parts)
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


def _obj(tmp_path: Path) -> Path:
    path = tmp_path / "thing.obj"
    _mesh().export(path)
    return path


def test_compile_then_check_round_trip(tmp_path: Path) -> None:
    """`navi compile` writes the file its summary describes (resolution, cube, source bounds, sizes), in
    JSON and in words, and `navi check` reads the same header back."""
    src = _obj(tmp_path)
    out = tmp_path / "thing.gmdag"
    res = runner.invoke(build_app(), ["compile", str(src), "-o", str(out), "--resolution", "30", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    g = read_gmdag(out)
    assert summary["output"] == str(out)
    assert summary["resolution"] == g.resolution == 32
    assert summary["voxel_size"] == g.voxel_size and tuple(summary["origin"]) == g.origin
    bounds = _mesh().bounds  # the source geometry's box, kept in the header as float32
    assert np.allclose(g.bounds_min, bounds[0], atol=1e-6) and np.allclose(g.bounds_max, bounds[1], atol=1e-6)
    cube_max = np.array(g.origin) + g.resolution * g.voxel_size
    assert np.all(np.array(g.origin) <= bounds[0]) and np.all(
        cube_max >= bounds[1]
    )  # the cube holds the scene
    assert summary["file_bytes"] == out.stat().st_size
    assert summary["compression"] == 32**3 * 4 / out.stat().st_size
    raw = 32 * len(g.nodes) + 730 * len(g.bricks)  # the octree uncompressed (docs/GMDAG.md)
    assert summary["payload_bytes"] == raw and summary["memory_compression"] == 32**3 * 4 / raw
    assert summary["leaked"] is False and summary["node_count"] == len(g.nodes)
    assert summary["brick_count"] == len(g.bricks)
    human = runner.invoke(
        build_app(), ["compile", str(src), "-o", str(out), "--resolution", "16", "--seed", "0,0,2"]
    )
    assert human.exit_code == 0, human.output
    g = read_gmdag(out)
    size = out.stat().st_size
    assert g.resolution == 16 and g.flags & FLAG_LEAK_FALLBACK == 0
    first, second, leak, timing = human.stdout.splitlines()
    assert first.startswith(f"{out}: {size / 1e6:.2f} MB, {16**3 * 4 / size:.1f}x smaller than dense float32")
    assert second == (
        f"  resolution 16^3, voxel {g.voxel_size:.4f} m, {len(g.nodes)} nodes, {len(g.bricks)} bricks"
    )
    assert leak.startswith("  leak check: ok (") and timing.startswith("  time: ")
    check = runner.invoke(build_app(), ["check", str(out), "--json"])
    assert check.exit_code == 0, check.output
    report = json.loads(check.stdout)
    assert report["valid"] is True
    entry = report["files"][0]
    assert entry["path"] == str(out) and entry["size_bytes"] == size
    assert entry["resolution"] == 16 and entry["voxel_size"] == g.voxel_size and entry["degenerate"] is None
    assert tuple(entry["origin"]) == g.origin and tuple(entry["bounds_min"]) == g.bounds_min
    assert tuple(entry["bounds_max"]) == g.bounds_max
    assert (entry["node_count"], entry["brick_count"]) == (len(g.nodes), len(g.bricks))
    assert entry["non_finite"] == 0 and entry["has_free"] and entry["has_solid"]
    assert entry["version"] == 2 and entry["compression"] > entry["memory_compression"]


def test_check_fails_on_any_invalid_file(tmp_path: Path) -> None:
    """`navi check` describes a valid file from its header, names a truncated or missing one INVALID with
    the reader's error, and exits 1 when any file is invalid."""
    src = _obj(tmp_path)
    good = tmp_path / "good.gmdag"
    made = runner.invoke(build_app(), ["compile", str(src), "-o", str(good), "--resolution", "16"])
    assert made.exit_code == 0, made.output
    g = read_gmdag(good)
    assert g.resolution == 16
    bad = tmp_path / "bad.gmdag"
    bad.write_bytes(good.read_bytes()[:-7])
    with pytest.raises(GmdagError) as reader:
        read_gmdag(bad)
    res = runner.invoke(build_app(), ["check", str(good), str(bad)])
    assert res.exit_code == 1
    valid, invalid = res.stdout.splitlines()
    assert valid.startswith(
        f"{good}: valid, resolution 16, voxel_size {g.voxel_size:.6g} m, "
        f"origin {tuple(round(v, 4) for v in g.origin)}, {len(g.nodes)} nodes, {len(g.bricks)} bricks"
    ), valid
    assert invalid == f"{bad}: INVALID: {reader.value}"
    missing = runner.invoke(build_app(), ["check", str(tmp_path / "nope.gmdag"), "--json"])
    assert missing.exit_code == 1
    (entry,) = json.loads(missing.stdout)["files"]
    assert json.loads(missing.stdout)["valid"] is False and entry["valid"] is False
    assert entry["error"].startswith("cannot read: ") and entry["resolution"] is None


def test_bad_input_is_one_line_and_exit_2(tmp_path: Path) -> None:
    """A missing source or a malformed --seed is one usage line naming the problem, exit 2, no file."""
    res = runner.invoke(
        build_app(), ["compile", str(tmp_path / "missing.obj"), "-o", str(tmp_path / "x.gmdag")]
    )
    assert res.exit_code == 2 and "not found" in res.output and "Traceback" not in res.output
    src = _obj(tmp_path)
    res = runner.invoke(build_app(), ["compile", str(src), "-o", str(tmp_path / "x.gmdag"), "--seed", "1,2"])
    assert res.exit_code == 2 and "x,y,z" in res.output
    assert not (tmp_path / "x.gmdag").exists()


def test_bench_compile_prints_one_json_object(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`navi bench compile` writes nothing and reports the stats of the compile `navi compile` makes of the
    same source."""
    monkeypatch.chdir(tmp_path)
    src = _obj(tmp_path)
    res = runner.invoke(build_app(), ["bench", "compile", str(src), "--resolution", "16", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert sorted(tmp_path.iterdir()) == [src]  # timed, not written
    assert data["resolution"] == 16 and data["seconds_total"] > 0 and data["engine"] == "cpp"
    assert data["output"] is None and data["source"] == str(src) and data["device"] == "cpu"
    out = tmp_path / "thing.gmdag"
    made = runner.invoke(build_app(), ["compile", str(src), "-o", str(out), "--resolution", "16", "--json"])
    assert made.exit_code == 0, made.output
    compiled = json.loads(made.stdout)
    same = ("voxel_size", "origin", "triangles", "node_count", "brick_count", "file_bytes", "payload_bytes")
    assert {k: data[k] for k in same} == {k: compiled[k] for k in same}
    assert data["file_bytes"] == out.stat().st_size


def test_compile_drops_detached_scenery_unless_told_to_keep_it(tmp_path: Path) -> None:
    """A closed 20 m room with a seed inside and a box 200 m away: `navi compile` fits the cube to the
    room and says what it dropped; `--keep-detached` compiles both, in a cube ten times wider."""
    walls = []
    for axis in range(3):
        for side in (-1, 1):
            ext, centre = [20.5] * 3, [0.0, 0.0, 0.0]
            ext[axis], centre[axis] = 0.5, side * 10.0
            walls.append(trimesh.creation.box(ext, trimesh.transformations.translation_matrix(centre)))
    far = trimesh.creation.box((6.0, 6.0, 6.0), trimesh.transformations.translation_matrix((200.0, 0.0, 0.0)))
    src = tmp_path / "room.obj"
    trimesh.util.concatenate([*walls, far]).export(src)
    out = tmp_path / "room.gmdag"
    base = ["compile", str(src), "-o", str(out), "--resolution", "32", "--seed", "2,3,1"]
    fit = runner.invoke(build_app(), [*base, "--json"])
    assert fit.exit_code == 0, fit.output
    fitted = json.loads(fit.stdout)
    assert fitted["detached_parts"] == 1 and fitted["detached_triangles"] == 12 and not fitted["leaked"]
    assert read_gmdag(out).voxel_size == fitted["voxel_size"] < 0.8
    kept = json.loads(runner.invoke(build_app(), [*base, "--keep-detached", "--json"]).stdout)
    assert kept["detached_parts"] == 0 and kept["voxel_size"] > 6.0
    human = runner.invoke(build_app(), [*base, "--mesh-out", str(tmp_path / "room.npz")])
    assert "dropped 1 detached part(s), 12 triangles that no seed reaches" in human.stdout
    with np.load(tmp_path / "room.npz") as mesh:  # the surfaces the field measures: the room alone
        assert len(mesh["triangles"]) == 6 * 12 and mesh["vertices"][:, 0].max() < 11.0
