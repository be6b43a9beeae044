"""`navi raycast` and `navi bench trace` on the CPU."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_compiler.gmdag import write_gmdag
from navi_env.tracer.analytic_scenes import demo_room, free_points, random_directions
from navi_env.tracer.scene import load_scene
from navi_env.tracer.trace import trace


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    room = demo_room(32, 8.0)
    path = tmp_path_factory.mktemp("scenes") / "room.gmdag"
    write_gmdag(room.gmdag(spawns=free_points(room, 4, 0.5, seed=0)), path)
    return path


def _save(tmp: Path, name: str, a: np.ndarray) -> Path:
    p = tmp / name
    np.save(p, a)
    return p


def test_raycast_writes_the_traced_depth(scene_file: Path, tmp_path: Path) -> None:
    origins = free_points(demo_room(32, 8.0), 3, 0.5, seed=1).astype(np.float32)  # (N, 3)
    dirs = random_directions(20, seed=2).astype(np.float32)  # (R, 3)
    o, d = _save(tmp_path, "o.npy", origins), _save(tmp_path, "d.npy", dirs)
    out, sem = tmp_path / "depth.npy", tmp_path / "sem.npy"
    res = CliRunner().invoke(
        build_app(), ["raycast", str(scene_file), "--origins", str(o), "--dirs", str(d), "-o", str(out),
                      "--semantic-out", str(sem), "--horizon", "50"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    depth = np.load(out)
    expected = torch.empty(3, 20)  # (N, R) float32
    trace(load_scene(scene_file), torch.zeros(3, dtype=torch.int64), torch.from_numpy(origins),
          torch.from_numpy(dirs), out_depth=expected, horizon=50.0)  # fmt: skip
    assert depth.shape == (3, 20) and depth.dtype == np.float32
    assert np.array_equal(depth, expected.numpy())
    assert (np.load(sem) > 0).all()  # a closed room: every ray hits

    per_ray = np.repeat(dirs[None], 3, axis=0)  # (N, R, 3)
    d3 = _save(tmp_path, "d3.npy", per_ray)
    res = CliRunner().invoke(
        build_app(),
        [
            "raycast",
            str(scene_file),
            "--origins",
            str(o),
            "--dirs",
            str(d3),
            "-o",
            str(out),
            "--horizon",
            "50",
        ],
    )
    assert res.exit_code == 0 and np.array_equal(np.load(out), depth)


@pytest.mark.parametrize(
    ("origins", "dirs", "message"),
    [
        (np.zeros((3, 2), np.float32), np.eye(3, dtype=np.float32), "--origins must be (N, 3)"),
        (np.ones((3, 3), np.float32), np.ones((2, 4, 3), np.float32), "--dirs must be (R, 3) or (3, R, 3)"),
        (np.ones((3, 3), np.float32), np.zeros((4, 3), np.float32), "unit vectors"),
    ],
)
def test_raycast_rejects_bad_inputs_with_exit_2(
    scene_file: Path, tmp_path: Path, origins: np.ndarray, dirs: np.ndarray, message: str
) -> None:
    o, d = _save(tmp_path, "o.npy", origins), _save(tmp_path, "d.npy", dirs)
    res = CliRunner().invoke(build_app(), ["raycast", str(scene_file), "--origins", str(o), "--dirs", str(d),
                                           "-o", str(tmp_path / "x.npy")])  # fmt: skip
    assert res.exit_code == 2
    assert message in res.output
    assert "Traceback" not in res.output


def test_raycast_rejects_a_missing_scene(tmp_path: Path) -> None:
    o = _save(tmp_path, "o.npy", np.ones((1, 3), np.float32))
    d = _save(tmp_path, "d.npy", np.eye(3, dtype=np.float32))
    res = CliRunner().invoke(build_app(), ["raycast", str(tmp_path / "nope.gmdag"), "--origins", str(o), "--dirs",
                                           str(d), "-o", str(tmp_path / "x.npy")])  # fmt: skip
    assert res.exit_code == 2 and "error:" in res.output


def test_bench_trace_prints_one_json_object(scene_file: Path) -> None:
    res = CliRunner().invoke(
        build_app(),
        ["bench", "trace", "--gmdag", str(scene_file), "--agents", "4", "--device", "cpu", "--steps", "1",
         "--azimuth", "32", "--elevation", "8", "--json"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    result = json.loads(res.stdout.strip().splitlines()[-1])
    assert result["rays_per_agent"] == 256 and result["agents"] == 4
    assert result["grays_per_s"] > 0 and result["observations_per_s"] > 0
    assert 1.0 <= result["mean_steps"] <= result["p99_steps"] <= 256
    assert result["mean_steps"] <= result["warp_steps"] <= result["max_steps"]  # a warp: its longest ray
    assert result["warp_efficiency"] == pytest.approx(result["mean_steps"] / result["warp_steps"])
    assert result["hit_fraction"] == 1.0  # agents at spawns inside a closed room
    assert result["bytes_per_scene"] == load_scene(scene_file).infos[0].nbytes


@pytest.mark.parametrize("rays", [64, 70])
@pytest.mark.parametrize("ordered", [False, True])
def test_warp_steps_charge_each_ray_its_warps_longest(rays: int, ordered: bool) -> None:
    from navi_bench.trace import warp_steps, warp_steps_ref

    gen = torch.Generator().manual_seed(rays)
    steps = torch.randint(1, 40, (3, rays), generator=gen, dtype=torch.int32)  # (B, R) int32
    order = torch.randperm(rays, generator=gen).to(torch.int32) if ordered else None  # (R,) int32
    assert warp_steps(steps, order) == pytest.approx(warp_steps_ref(steps, order))
    assert warp_steps(steps, order) >= steps.float().mean()
    even = torch.full((2, rays), 7, dtype=torch.int32)  # every ray equally long: nothing is wasted
    assert warp_steps(even, order) == pytest.approx(7.0)
    one_long = torch.ones(1, 64, dtype=torch.int32)  # (1, 64): one long ray in the first warp
    one_long[0, 5] = 33
    assert warp_steps(one_long, None) == pytest.approx((32 * 33 + 32 * 1) / 64)


def test_spherical_pattern_layout() -> None:
    from navi_env.rays import spherical_directions

    d = spherical_directions(8, 4).view(8, 4, 3)  # (Az, El, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(8, 4))
    assert d[0, :, 1].abs().max() < 1e-6 and (d[0, :, 0] > 0).all()  # azimuth bin 0 looks along +X
    assert (d[2, :, 1] > 0.1).all()  # a quarter turn counter-clockwise looks along +Y
    assert (d[:, 0, 2] < -0.9).all() and (d[:, -1, 2] > 0.9).all()  # elevation bins run from down to up


def test_bench_trace_with_moving_obstacles(scene_file: Path) -> None:
    def run(k: int) -> dict[str, float]:
        res = CliRunner().invoke(
            build_app(),
            ["bench", "trace", "--gmdag", str(scene_file), "--agents", "8", "--device", "cpu", "--steps", "2",
             "--azimuth", "32", "--elevation", "8", "--obstacles", str(k), "--json"],
        )  # fmt: skip
        assert res.exit_code == 0, res.output
        return dict(json.loads(res.stdout.strip().splitlines()[-1]))

    plain, crowded = run(0), run(16)
    assert plain["obstacles_per_agent"] == 0 and plain["obstacle_hit_fraction"] == 0.0
    assert crowded["obstacles_per_agent"] == 16 and crowded["obstacle_hit_fraction"] > 0.05
    # Primitives end rays early: the walk takes fewer steps on average.
    assert crowded["mean_steps"] < plain["mean_steps"]


def test_bench_trace_over_a_folder_summarises_every_map(tmp_path: Path) -> None:
    """--corpus: one row per .gmdag (sorted), and a summary whose extremes, medians and target lists are
    those of the rows; the dense ratio is 4·R³ bytes over the scene's device bytes."""
    for name, size in (("big", 16.0), ("small", 4.0), ("mid", 8.0)):
        room = demo_room(32 if name != "small" else 16, size)
        write_gmdag(room.gmdag(spawns=free_points(room, 4, 0.1 * size, seed=0)), tmp_path / f"{name}.gmdag")
    (tmp_path / "notes.txt").write_text("not a scene")
    res = CliRunner().invoke(
        build_app(),
        ["bench", "trace", "--corpus", str(tmp_path), "--agents", "4", "--device", "cpu", "--steps", "1",
         "--azimuth", "32", "--elevation", "8", "--json"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout.strip().splitlines()[-1])
    rows, summary = report["maps"], report["summary"]
    assert [r["scene"] for r in rows] == ["big", "mid", "small"] and summary["maps"] == 3
    for r in rows:
        assert r["dense_ratio"] == 4 * r["resolution"] ** 3 / r["bytes_per_scene"]
    for key in (
        "grays_per_s",
        "mean_steps",
        "p99_steps",
        "warp_efficiency",
        "bytes_per_scene",
        "dense_ratio",
    ):
        values = sorted(r[key] for r in rows)
        s = summary[key]
        assert (s["min"], s["median"], s["max"]) == (values[0], values[1], values[2]), key
        assert {r["scene"]: r[key] for r in rows}[s["min_scene"]] == s["min"]
    assert summary["below_target_grays"] == [r["scene"] for r in rows]  # the CPU is far below 10 G rays/s
    assert summary["below_target_dense_ratio"] == [r["scene"] for r in rows if r["dense_ratio"] < 100]
    assert "[3/3]" in res.stderr  # a progress line per map


def test_bench_trace_needs_one_of_gmdag_or_corpus(scene_file: Path, tmp_path: Path) -> None:
    app = build_app()
    for args in ([], ["--gmdag", str(scene_file), "--corpus", str(tmp_path)], ["--corpus", str(tmp_path)]):
        res = CliRunner().invoke(app, ["bench", "trace", "--device", "cpu", *args])
        assert res.exit_code == 2 and "error:" in res.output, args
