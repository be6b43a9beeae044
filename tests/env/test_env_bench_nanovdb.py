"""The NanoVDB anchor of `navi bench trace --vs-nanovdb`: its narrow band holds the scene's own samples,
and its march agrees with the reference tracer on a small scene."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from navi_bench.nanovdb import TILE, TILE_REACH, candidate_tiles, narrow_band
from navi_bench.trace import TraceBenchConfig, place_agents
from navi_compiler.compile import compile_scene
from navi_compiler.gmdag import write_gmdag
from navi_compiler.ingest.procedural import generate_scene
from navi_env.rays import spherical_directions
from navi_env.tracer.scene import SceneCorpus, load_scene
from navi_env.tracer.trace import sample_distance
from navi_env.tracer.trace_ref import trace_ref

needs_warp = pytest.mark.skipif(
    importlib.util.find_spec("warp") is None, reason="warp-lang is not installed (the anchor's only need)"
)
CFG = TraceBenchConfig(agents=8, device="cpu", launches=2, warmup=1, azimuth_bins=32, elevation_bins=8)


@pytest.fixture(scope="module")
def rooms(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A procedural rooms scene at 64^3 (walls, doors and floors: hits at every range)."""
    path = tmp_path_factory.mktemp("nanovdb") / "rooms.gmdag"
    gmdag, _ = compile_scene(generate_scene("rooms", 0), resolution=64)
    write_gmdag(gmdag, path)
    return path


def reference_depth(corpus: SceneCorpus, cfg: TraceBenchConfig) -> np.ndarray:
    """(B, R) depth of the benchmark's agents through the reference tracer."""
    agents = place_agents(corpus, cfg.agents, cfg.clearance_voxels, cfg.seed)
    pattern = spherical_directions(cfg.azimuth_bins, cfg.elevation_bins)  # (R, 3)
    depth = torch.empty(cfg.agents, len(pattern))  # (B, R)
    trace_ref(corpus, agents.scene_ids, agents.origins, pattern, yaw=agents.yaw, out_depth=depth,
              max_steps=cfg.max_steps, horizon=cfg.horizon, hit_slope=cfg.hit_slope)  # fmt: skip
    return depth.numpy()


def test_band_tiles_hold_every_sample_near_the_surface(rooms: Path) -> None:
    """The band's tiles are exactly those holding a lattice sample within the band (fewer than the
    candidates found from the tiles' centres), and a wider band allocates more."""
    corpus = load_scene(rooms, "cpu")
    info = corpus.infos[0]
    n = info.resolution + 1
    ijk = torch.stack(torch.meshgrid(*[torch.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)  # (n^3, 3)
    pts = torch.from_numpy(info.cube_min).float() + ijk.float() * info.voxel_size  # (n^3, 3) meters
    d = sample_distance(corpus, torch.zeros(len(pts), dtype=torch.int64), pts) / info.voxel_size  # (n^3,)
    tiles = {tuple(t) for t in narrow_band(corpus, 3.0)[0].tolist()}
    near = ijk[d.abs() <= 3.0]  # (K, 3) samples in the band
    assert len(near) > 0
    assert all(tuple((v // TILE * TILE).tolist()) in tiles for v in near)
    # and no other tile: each holds a sample within the band (the candidates' slack is left out)
    assert tiles == {tuple((v // TILE * TILE).tolist()) for v in near}
    assert len(candidate_tiles(corpus, 3.0)) > len(tiles)
    assert len(narrow_band(corpus, 8.0)[0]) > len(tiles)
    assert TILE_REACH > (TILE - 1) / 2 * 3**0.5


@needs_warp
def test_nanovdb_march_agrees_with_the_reference_tracer(rooms: Path) -> None:
    from navi_bench.nanovdb import nanovdb_depth

    corpus = load_scene(rooms, "cpu")
    voxel = corpus.infos[0].voxel_size
    ref = reference_depth(corpus, CFG)  # (B, R)
    for band in (3.0, 8.0):
        for sampling in ("linear", "closest-far"):
            depth, steps = nanovdb_depth(corpus, CFG, band, sampling=sampling)  # (B, R) each
            hit, ref_hit = depth < CFG.horizon, ref < CFG.horizon
            assert (hit == ref_hit).mean() >= 0.995
            both = hit & ref_hit
            assert both.mean() > 0.5  # walls in most directions
            diff = np.abs(depth[both] - ref[both]) / voxel  # voxels
            assert np.median(diff) < 0.01 and np.quantile(diff, 0.99) < 0.5
            assert steps.min() >= 1 and steps.max() <= CFG.max_steps


@needs_warp
def test_nanovdb_nearest_sample_steps_stop_where_trilinear_steps_do(rooms: Path) -> None:
    """The nearest-sample bound never steps past a surface: "closest-far" ends every ray within a
    hundredth of a voxel of the trilinear march at the median, and hits what it hits."""
    from navi_bench.nanovdb import nanovdb_depth

    corpus = load_scene(rooms, "cpu")
    voxel = corpus.infos[0].voxel_size
    linear, _ = nanovdb_depth(corpus, CFG, 8.0)  # (B, R)
    far, _ = nanovdb_depth(corpus, CFG, 8.0, sampling="closest-far")  # (B, R)
    assert ((linear < CFG.horizon) == (far < CFG.horizon)).all()
    diff = np.abs(far - linear) / voxel  # (B, R) voxels
    assert np.median(diff) < 0.01 and diff.max() < 0.5


@needs_warp
def test_a_coarser_band_holds_fewer_tiles_and_the_same_walls(rooms: Path) -> None:
    """At voxel scale 2 the band samples the same field on a lattice twice as coarse: fewer tiles,
    twice the voxel, and rays still end on the reference tracer's walls at the median."""
    from navi_bench.nanovdb import lattice, nanovdb_depth

    corpus = load_scene(rooms, "cpu")
    info = corpus.infos[0]
    assert lattice(corpus, 2) == (info.resolution // 2, 2 * info.voxel_size)
    assert len(narrow_band(corpus, 8.0, 2)[0]) < len(narrow_band(corpus, 8.0)[0]) / 2
    ref = reference_depth(corpus, CFG)  # (B, R)
    depth, _ = nanovdb_depth(corpus, CFG, 8.0, scale=2)  # (B, R)
    hit, ref_hit = depth < CFG.horizon, ref < CFG.horizon
    assert (hit == ref_hit).mean() >= 0.99
    both = hit & ref_hit
    assert np.median(np.abs(depth[both] - ref[both])) < 0.5 * info.voxel_size
    with pytest.raises(ValueError, match="at least 1"):
        lattice(corpus, 0)


@needs_warp
def test_bench_trace_vs_nanovdb_reports_each_band(rooms: Path) -> None:
    from typer.testing import CliRunner

    from navi.cli import build_app

    args = f"bench trace --gmdag {rooms} --device cpu --agents 4 --steps 1 --azimuth 32 --elevation 8"
    result = CliRunner().invoke(
        build_app(), [*args.split(), "--vs-nanovdb", "--nanovdb-bands", "3,8", "--json"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout.strip().splitlines()[-1])
    bands = report["nanovdb"]
    assert [b["band_voxels"] for b in bands] == [3.0, 8.0]
    assert bands[0]["tiles"] < bands[1]["tiles"] and bands[0]["device_bytes"] < bands[1]["device_bytes"]
    for b in bands:
        assert b["grays_per_s"] > 0 and b["hit_disagreement"] <= 0.005
        assert b["median_abs_depth_diff_m"] is not None and b["median_abs_depth_diff_m"] < 0.01
        assert (b["voxel_scale"], b["sampling"]) == (1, "linear")
    more = ["--vs-nanovdb", "--nanovdb-bands", "8", "--nanovdb-scales", "1,2", "--nanovdb-sampling",
            "linear,closest-far", "--json"]  # fmt: skip
    result = CliRunner().invoke(build_app(), [*args.split(), *more])
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout.strip().splitlines()[-1])["nanovdb"]
    assert [(r["voxel_scale"], r["sampling"]) for r in rows] == [
        (1, "linear"), (1, "closest-far"), (2, "linear"), (2, "closest-far")
    ]  # fmt: skip
    assert rows[0]["tiles"] == rows[1]["tiles"] > rows[2]["tiles"] == rows[3]["tiles"]
    assert rows[2]["voxel_m"] == 2 * rows[0]["voxel_m"]


def test_bench_trace_vs_nanovdb_rejects_bad_options(rooms: Path) -> None:
    from typer.testing import CliRunner

    from navi.cli import build_app

    base = ["bench", "trace", "--gmdag", str(rooms), "--device", "cpu", "--vs-nanovdb"]
    for extra, says in (
        (["--nanovdb-bands", "3,wide"], "--nanovdb-bands expects numbers"),
        (["--nanovdb-bands", "0"], "every one above 0"),
        (["--obstacles", "2"], "leave out --obstacles"),
        (["--nanovdb-scales", "1.5"], "--nanovdb-scales expects whole numbers"),
        (["--nanovdb-scales", "0"], "every one 1 or more"),
        (["--nanovdb-sampling", "cubic"], "--nanovdb-sampling takes linear or closest-far"),
    ):
        result = CliRunner().invoke(build_app(), base + extra)
        assert result.exit_code == 2 and says in result.stderr, result.output
