"""`navi bench trace --vs-warp`: the benchmark's rays cast through a Warp BVH of the source mesh.

Only when `warp` (warp-lang) imports; otherwise `WarpUnavailable` with the reason. The same agents,
yaws and 256x48 pattern as `bench_trace`, world-space rays prepared once on the host, one Warp
`mesh_query_ray` per ray; timing after warm-up with device synchronisation around the launches.

Shapes: V vertices, F triangles, P = B * R rays.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from navi_env.bench_trace import TraceBenchConfig, place_agents, rays_for_warp
from navi_env.rays import spherical_directions
from navi_env.scene import SceneCorpus
from navi_env.trace import trace
from navi_env.warp_kernel import ray_kernel


class WarpUnavailable(RuntimeError):
    """Warp cannot run this comparison (not installed, or no mesh)."""


def load_mesh_npz(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """vertices (V, 3) float32 and triangles (F, 3) int32 from an .npz with those two arrays."""
    with np.load(path) as data:
        if "vertices" not in data or "triangles" not in data:
            raise ValueError(f"{path} must hold arrays 'vertices' (V, 3) and 'triangles' (F, 3)")
        v = np.ascontiguousarray(data["vertices"], np.float32)  # (V, 3)
        f = np.ascontiguousarray(data["triangles"], np.int32)  # (F, 3)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{path}: vertices must be (V, 3) and triangles (F, 3), got {v.shape} and {f.shape}")
    return v, f


def bench_warp(
    corpus: SceneCorpus, cfg: TraceBenchConfig, mesh_path: Path, tracer_ms: float
) -> dict[str, object]:
    """Time Warp on the benchmark's rays; report its rate, the tracer/Warp speed ratio and agreement."""
    try:
        import warp as wp
    except ImportError as exc:
        raise WarpUnavailable(f"warp-lang is not installed ({exc}); pip install warp-lang") from None
    vertices, triangles = load_mesh_npz(mesh_path)
    dev = corpus.device
    wp_device = f"cuda:{dev.index or 0}" if dev.type == "cuda" else "cpu"
    wp.config.quiet = True  # keep stdout for the one JSON object
    wp.init()
    origins, dirs = rays_for_warp(corpus, cfg)  # (P, 3), (P, 3) float32
    mesh = wp.Mesh(
        points=wp.array(vertices, dtype=wp.vec3, device=wp_device),
        indices=wp.array(triangles.reshape(-1), dtype=wp.int32, device=wp_device),
    )
    o = wp.array(origins, dtype=wp.vec3, device=wp_device)
    d = wp.array(dirs, dtype=wp.vec3, device=wp_device)
    out = wp.zeros(len(origins), dtype=float, device=wp_device)
    kernel = ray_kernel(wp)

    def launch() -> None:
        wp.launch(kernel, dim=len(origins), inputs=[mesh.id, o, d, cfg.horizon, out], device=wp_device)

    for _ in range(cfg.warmup):
        launch()
    wp.synchronize_device(wp_device)
    t0 = time.perf_counter()
    for _ in range(cfg.launches):
        launch()
    wp.synchronize_device(wp_device)
    seconds = (time.perf_counter() - t0) / cfg.launches
    warp_depth = out.numpy().reshape(cfg.agents, -1)  # (B, R)
    ours = _tracer_depth(corpus, cfg)  # (B, R)
    both = (warp_depth < cfg.horizon) & (ours < cfg.horizon)
    return {
        "ms_per_launch": seconds * 1e3,
        "grays_per_s": len(origins) / seconds / 1e9,
        "speedup_tracer_vs_warp": seconds * 1e3 / tracer_ms,
        "median_abs_depth_diff_m": float(np.median(np.abs(warp_depth[both] - ours[both])))
        if both.any()
        else None,
        "hit_disagreement": float(((warp_depth < cfg.horizon) != (ours < cfg.horizon)).mean()),
        "triangles": len(triangles),
    }


def _tracer_depth(corpus: SceneCorpus, cfg: TraceBenchConfig) -> np.ndarray:
    """(B, R) tracer depth for the benchmark's agents, on the host."""
    agents = place_agents(corpus, cfg.agents, cfg.clearance_voxels, cfg.seed)
    pattern = spherical_directions(cfg.azimuth_bins, cfg.elevation_bins, corpus.device)  # (R, 3)
    depth = torch.empty(cfg.agents, len(pattern), device=corpus.device)  # (B, R) float32
    trace(corpus, agents.scene_ids, agents.origins, pattern, yaw=agents.yaw, out_depth=depth,
          max_steps=cfg.max_steps, horizon=cfg.horizon)  # fmt: skip
    return depth.cpu().numpy()
