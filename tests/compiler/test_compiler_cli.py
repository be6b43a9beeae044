"""`navi compile`, `navi check` and `navi bench compile` through the root command."""

from __future__ import annotations

import json
from pathlib import Path

import trimesh
from typer.testing import CliRunner

from navi.cli import build_app
from navi_compiler.gmdag import read_gmdag

runner = CliRunner()


def _obj(tmp_path: Path) -> Path:
    mesh = trimesh.util.concatenate(
        [
            trimesh.creation.box((1.0, 1.0, 1.0)),
            trimesh.creation.icosphere(radius=0.3).apply_translation((1.2, 0, 0)),
        ]
    )
    path = tmp_path / "thing.obj"
    mesh.export(path)
    return path


def test_compile_then_check_round_trip(tmp_path: Path) -> None:
    src = _obj(tmp_path)
    out = tmp_path / "thing.gmdag"
    res = runner.invoke(build_app(), ["compile", str(src), "-o", str(out), "--resolution", "30", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    g = read_gmdag(out)
    assert summary["resolution"] == g.resolution == 32
    assert summary["file_bytes"] == out.stat().st_size
    assert summary["compression"] == 32**3 * 4 / out.stat().st_size
    raw = 32 * len(g.nodes) + 730 * len(g.bricks)  # the octree uncompressed (docs/GMDAG.md)
    assert summary["payload_bytes"] == raw and summary["memory_compression"] == 32**3 * 4 / raw
    assert summary["leaked"] is False and summary["node_count"] == len(g.nodes)
    human = runner.invoke(
        build_app(), ["compile", str(src), "-o", str(out), "--resolution", "16", "--seed", "0,0,2"]
    )
    assert (
        human.exit_code == 0 and "leak check" in human.stdout and "smaller than dense float32" in human.stdout
    )
    check = runner.invoke(build_app(), ["check", str(out), "--json"])
    assert check.exit_code == 0
    report = json.loads(check.stdout)
    assert report["valid"] is True
    entry = report["files"][0]
    assert entry["resolution"] == 16 and entry["voxel_size"] > 0 and entry["degenerate"] is None
    assert entry["non_finite"] == 0 and entry["has_free"] and entry["has_solid"]
    assert entry["version"] == 2 and entry["compression"] > entry["memory_compression"]


def test_check_fails_on_any_invalid_file(tmp_path: Path) -> None:
    src = _obj(tmp_path)
    good = tmp_path / "good.gmdag"
    assert (
        runner.invoke(build_app(), ["compile", str(src), "-o", str(good), "--resolution", "16"]).exit_code
        == 0
    )
    bad = tmp_path / "bad.gmdag"
    bad.write_bytes(good.read_bytes()[:-7])
    res = runner.invoke(build_app(), ["check", str(good), str(bad)])
    assert res.exit_code == 1
    assert "INVALID" in res.stdout and "valid, resolution 16" in res.stdout
    missing = runner.invoke(build_app(), ["check", str(tmp_path / "nope.gmdag"), "--json"])
    assert missing.exit_code == 1 and json.loads(missing.stdout)["valid"] is False


def test_bad_input_is_one_line_and_exit_2(tmp_path: Path) -> None:
    res = runner.invoke(
        build_app(), ["compile", str(tmp_path / "missing.obj"), "-o", str(tmp_path / "x.gmdag")]
    )
    assert res.exit_code == 2 and "not found" in res.output and "Traceback" not in res.output
    src = _obj(tmp_path)
    res = runner.invoke(build_app(), ["compile", str(src), "-o", str(tmp_path / "x.gmdag"), "--seed", "1,2"])
    assert res.exit_code == 2 and "x,y,z" in res.output


def test_bench_compile_prints_one_json_object(tmp_path: Path) -> None:
    src = _obj(tmp_path)
    res = runner.invoke(build_app(), ["bench", "compile", str(src), "--resolution", "16", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["resolution"] == 16 and data["seconds_total"] > 0 and data["engine"] == "cpp"
