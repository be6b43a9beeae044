"""The Warp anchor of `navi bench trace --vs-warp --obstacles K`: primitives as box meshes (no Warp
needed), and the refit-and-cast path where warp-lang is installed."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from navi_bench.trace import TraceBenchConfig, bench_trace
from navi_bench.warp import obstacle_boxes
from navi_env.tracer import primitives as ob


def test_obstacle_boxes_wrap_every_primitive_with_outward_triangles() -> None:
    origins = torch.zeros(3, 3)
    prims = ob.scatter(origins, 8, torch.Generator().manual_seed(0))  # (3, 8, 16) all four kinds
    verts, tris = obstacle_boxes(prims)
    assert verts.shape == (3 * 8 * 8, 3) and tris.shape == (3 * 8 * 12, 3)
    assert tris.min() == 0 and tris.max() == len(verts) - 1
    recs = prims.reshape(-1, ob.WORDS)
    for m, rec in enumerate(recs.tolist()):
        corners = verts[8 * m : 8 * m + 8].astype(np.float64)
        d = np.array([ob.distance_one(rec, c.tolist()) for c in corners])
        if int(rec[ob.KIND]) in (ob.BOX, ob.OBB):
            assert np.abs(d).max() < 1e-4  # the box itself: corners on its surface
        else:
            assert d.min() > 0.0  # spheres and capsules inside their boxes
        # a point inside the primitive lies inside the box: the centre is behind every face
        center = np.array(rec[ob.CENTER : ob.CENTER + 3])
        for a, b, c in verts[tris[12 * m : 12 * m + 12]].astype(np.float64):
            normal = np.cross(b - a, c - a)
            assert float(normal @ (a - center)) > 0.0  # counter-clockwise seen from outside


@pytest.mark.skipif(
    importlib.util.find_spec("warp") is None, reason="warp-lang is not installed (the anchor's only need)"
)
def test_warp_refit_anchor_casts_through_moving_boxes(tmp_path: Path) -> None:
    from navi_bench.warp import bench_warp
    from navi_compiler.compile import compile_scene
    from navi_compiler.gmdag import write_gmdag
    from navi_compiler.ingest.procedural import generate_scene
    from navi_env.tracer.scene import load_scene

    scene = generate_scene("hall", 0)
    np.savez(
        tmp_path / "hall.npz",
        vertices=scene.vertices.astype(np.float32),
        triangles=scene.faces.astype(np.int32),
    )
    gmdag, _ = compile_scene(scene, resolution=64)
    write_gmdag(gmdag, tmp_path / "hall.gmdag")
    corpus = load_scene(tmp_path / "hall.gmdag", "cpu")
    results: dict[tuple[int, int], dict[str, Any]] = {}
    for agents, k in ((4, 0), (4, 4), (1, 8)):
        cfg = TraceBenchConfig(agents=agents, device="cpu", launches=2, warmup=1, azimuth_bins=32,
                               elevation_bins=8, obstacles=k)  # fmt: skip
        ours = bench_trace(corpus, cfg)
        results[agents, k] = bench_warp(corpus, cfg, tmp_path / "hall.npz", ours.ms_per_launch)
    static = results[4, 0]
    voxel = corpus.infos[0].voxel_size
    assert static["median_abs_depth_diff_m"] is not None and static["median_abs_depth_diff_m"] < 0.25 * voxel
    assert static["hit_disagreement"] == 0.0  # a closed hall: every ray ends on a wall in both
    shared = results[4, 4]
    assert shared["refit_every_launch"] and shared["obstacle_triangles"] == 4 * 4 * 12
    assert shared["triangles"] == static["triangles"] + 4 * 4 * 12
    assert shared["median_abs_depth_diff_m"] is None  # every agent sees every agent's boxes: not comparable
    # one agent: the mesh holds only its own 8 boxes (two boxes, two oriented boxes among them), moved and
    # refit on every launch, then put back; where the tracer's primitives stop a ray short of the walls,
    # Warp's boxes stop it at the same depth, well within the 1 cm a launch moves them
    alone = results[1, 8]
    assert alone["obstacle_rays"] >= 10, alone
    assert alone["obstacle_median_abs_depth_diff_m"] < 2e-3, alone
    assert alone["median_abs_depth_diff_m"] < 0.25 * voxel and alone["hit_disagreement"] == 0.0


def test_compile_mesh_out_holds_the_surfaces_the_tracer_sees(tmp_path: Path) -> None:
    """`navi compile --mesh-out` writes drawn and barrier triangles: rays through an open scene's lid
    end on it in the tracer and in the exported mesh alike, while the drawn triangles alone let them
    escape (the Warp anchor would then cast cheaper misses, not the same rays)."""
    from typer.testing import CliRunner

    from navi.cli import build_app
    from navi_bench.warp import load_mesh_npz
    from navi_compiler.ingest.procedural import generate_scene, write_scene_mesh
    from navi_env.tracer.accuracy import mesh_hits
    from navi_env.tracer.scene import load_scene
    from navi_env.tracer.trace import trace

    scene = generate_scene("yard", 4)  # walls and crates under an undrawn lid
    src = write_scene_mesh(scene, tmp_path / "yard.obj")
    out, mesh = tmp_path / "yard.gmdag", tmp_path / "yard.npz"
    runner = CliRunner()
    res = runner.invoke(
        build_app(), ["compile", str(src), "-o", str(out), "--resolution", "64", "--mesh-out", str(mesh)]
    )
    assert res.exit_code == 0, res.output
    vertices, triangles = load_mesh_npz(mesh)
    assert vertices.dtype == np.float32 and triangles.dtype == np.int32
    assert len(triangles) == len(scene.faces) + len(scene.barrier_faces) and len(scene.barrier_faces) > 0

    corpus = load_scene(out, "cpu")
    origins = torch.tensor(scene.seeds[:4], dtype=torch.float32)  # (B, 3) known-free points
    gen = torch.Generator().manual_seed(0)
    dirs = torch.randn(64, 3, generator=gen)  # (R, 3)
    dirs[:, 2] = dirs[:, 2].abs() + 0.5  # upwards, towards the lid
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    depth = torch.empty(len(origins), len(dirs))  # (B, R) float32 meters
    trace(corpus, torch.zeros(len(origins), dtype=torch.int64), origins, dirs, out_depth=depth, horizon=1e3)
    o = origins[:, None, :].expand(-1, len(dirs), -1).reshape(-1, 3)  # (B*R, 3)
    d = dirs[None].expand(len(origins), -1, -1).reshape(-1, 3)  # (B*R, 3)
    tri = torch.from_numpy(vertices[triangles]).double()  # (F + Fb, 3, 3)
    drawn = torch.from_numpy(scene.vertices[scene.faces])  # (F, 3, 3)
    with_lid, drawn_only = mesh_hits(o, d, tri), mesh_hits(o, d, drawn)  # (B*R,) float64 each
    ours = depth.reshape(-1).double()  # (B*R,)
    voxel = corpus.infos[0].voxel_size
    assert bool(torch.isfinite(with_lid).all())  # every upward ray meets a wall, a crate or the lid
    assert float(((ours - with_lid).abs() < 1.5 * voxel).double().mean()) > 0.95
    assert float(torch.isinf(drawn_only).double().mean()) > 0.3  # without the lid many escape

    bad = runner.invoke(
        build_app(), ["compile", str(src), "-o", str(out), "--mesh-out", str(tmp_path / "m.obj")]
    )
    assert bad.exit_code == 2 and ".npz" in bad.output
