"""`navi bench trace --vs-warp`: the benchmark's rays cast through a Warp BVH of the source mesh.

Only when `warp` (warp-lang) imports; otherwise `WarpUnavailable` with the reason. The same agents,
yaws and 256x48 pattern as `bench_trace`, world-space rays prepared once on the host, one Warp
`mesh_query_ray` per ray; timing after warm-up with device synchronisation around the launches.

With `--obstacles K` the anchor is what a BVH simulator does for moving geometry: the same B x K
primitives as `bench_trace` (navi_env.tracer.primitives.scatter), each as the 12 triangles of its box (spheres
and capsules as their bounding boxes), appended to the scene mesh; before every cast their vertices
move like ours (+-1 cm) and the BVH is refit (`Mesh.refit`). One shared mesh: every agent's rays see
every agent's boxes (Warp has no per-environment visibility short of a mesh per environment), so the
depths are compared with the tracer's only for one agent, whose boxes are then all the mesh holds: after
the timed launches the boxes go back where they were placed, the BVH is refit and cast once more.

Shapes: V vertices, F triangles, P = B * R rays.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from navi_bench.trace import TraceBenchConfig, place_agents, rays_for_warp, tracer_depth
from navi_bench.warp_kernel import ray_kernel, shift_kernel
from navi_env.tracer import primitives as obstacles
from navi_env.tracer.scene import SceneCorpus


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


BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)  # (8, 3)
BOX_TRIANGLES = np.array(
    [[0, 3, 2], [0, 1, 3], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 7, 6], [2, 3, 7], [0, 6, 4], [0, 2, 6], [1, 5, 7], [1, 7, 3]],
    np.int32,
)  # fmt: skip
"""(12, 3) triangles of the unit box over BOX_CORNERS (corner index = 4 x + 2 y + z, bits of +1),
counter-clockwise seen from outside."""


def obstacle_boxes(prims: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Box meshes of primitive records (B, K, 16): vertices (B*K*8, 3) float32 and triangles (B*K*12, 3)
    int32 (indices from 0). Boxes and oriented boxes are themselves; a sphere becomes the cube around it
    and a capsule the box around it along its axis."""
    rec = prims.reshape(-1, obstacles.WORDS).double().cpu().numpy()  # (M, 16)
    m = len(rec)
    kind, rad = rec[:, obstacles.KIND], rec[:, obstacles.RADIUS]  # (M,)
    center, axis = (
        rec[:, obstacles.CENTER : obstacles.CENTER + 3],
        rec[:, obstacles.AXIS : obstacles.AXIS + 3],
    )
    w, x, y, z = (rec[:, obstacles.QUAT + i] for i in range(4))  # (M,) each
    rot = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )  # (M, 3, 3) box frame -> world (oriented boxes)
    half = axis.copy()  # (M, 3) boxes: their half extents
    eye = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()  # (M, 3, 3)
    sphere, capsule, obb = kind == obstacles.SPHERE, kind == obstacles.CAPSULE, kind == obstacles.OBB
    half[sphere] = rad[sphere, None]
    length = np.linalg.norm(axis, axis=1)  # (M,)
    u = axis / np.maximum(length, 1e-12)[:, None]  # (M, 3) capsule axis
    helper = np.where(np.abs(u[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])  # (M, 3)
    e1 = np.cross(u, helper)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1), 1e-12)[:, None]
    e2 = np.cross(u, e1)
    frame = np.stack([e1, e2, u], axis=2)  # (M, 3, 3) columns: capsule frame -> world
    half[capsule] = np.stack([rad, rad, length + rad], 1)[capsule]
    basis = np.where(obb[:, None, None], rot, np.where(capsule[:, None, None], frame, eye))  # (M, 3, 3)
    local = BOX_CORNERS[None, :, :] * half[:, None, :]  # (M, 8, 3)
    verts = center[:, None, :] + np.einsum("mij,mcj->mci", basis, local)  # (M, 8, 3)
    tris = BOX_TRIANGLES[None, :, :] + 8 * np.arange(m, dtype=np.int32)[:, None, None]  # (M, 12, 3)
    return verts.reshape(-1, 3).astype(np.float32), tris.reshape(-1, 3).astype(np.int32)


def bench_warp(
    corpus: SceneCorpus, cfg: TraceBenchConfig, mesh_path: Path, tracer_ms: float
) -> dict[str, object]:
    """Time Warp on the benchmark's rays; report its rate, the tracer/Warp speed ratio and agreement."""
    try:
        import warp as wp
    except ImportError as exc:
        raise WarpUnavailable(f"warp-lang is not installed ({exc}); pip install warp-lang") from None
    vertices, triangles = load_mesh_npz(mesh_path)
    static_vertices = len(vertices)
    prims: torch.Tensor | None = None
    if cfg.obstacles > 0:
        agents = place_agents(corpus, cfg.agents, cfg.clearance_voxels, cfg.seed)
        prims = obstacles.scatter(
            agents.origins.cpu(), cfg.obstacles, torch.Generator().manual_seed(cfg.seed + 1)
        )
        box_v, box_f = obstacle_boxes(prims)  # the same primitives as bench_trace, as boxes
        triangles = np.concatenate([triangles, box_f + static_vertices]).astype(np.int32)
        vertices = np.concatenate([vertices, box_v]).astype(np.float32)
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
    moving = len(vertices) - static_vertices  # obstacle vertices, after the static ones
    steps = [
        wp.array(np.full((1, 3), s, np.float32), dtype=wp.vec3, device=wp_device) for s in (0.01, -0.01)
    ]  # meters per launch, back and forth
    shift = shift_kernel(wp)
    launches = [0]

    def launch() -> None:
        if moving:
            step = steps[launches[0] % 2]
            launches[0] += 1
            wp.launch(shift, dim=moving, inputs=[mesh.points, static_vertices, step], device=wp_device)
            mesh.refit()
        wp.launch(kernel, dim=len(origins), inputs=[mesh.id, o, d, cfg.horizon, out], device=wp_device)

    for _ in range(cfg.warmup):
        launch()
    wp.synchronize_device(wp_device)
    t0 = time.perf_counter()
    for _ in range(cfg.launches):
        launch()
    wp.synchronize_device(wp_device)
    seconds = (time.perf_counter() - t0) / cfg.launches
    result: dict[str, object] = {
        "ms_per_launch": seconds * 1e3,
        "grays_per_s": len(origins) / seconds / 1e9,
        "speedup_tracer_vs_warp": seconds * 1e3 / tracer_ms,
        "triangles": len(triangles),
    }
    if moving:
        if launches[0] % 2:  # an odd number of launches left the boxes 1 cm off: back where they were placed
            wp.launch(shift, dim=moving, inputs=[mesh.points, static_vertices, steps[1]], device=wp_device)
            mesh.refit()
        wp.launch(kernel, dim=len(origins), inputs=[mesh.id, o, d, cfg.horizon, out], device=wp_device)
        result |= {
            "obstacle_triangles": len(triangles) - len(load_mesh_npz(mesh_path)[1]),
            "refit_every_launch": True,
        }
    warp_depth = out.numpy().reshape(cfg.agents, -1)  # (B, R)
    result["hit_fraction"] = float((warp_depth < cfg.horizon).mean())
    if moving and cfg.agents > 1:  # each agent's rays see everyone's boxes: no depth to compare with
        return result | {"median_abs_depth_diff_m": None, "hit_disagreement": None}
    ours = tracer_depth(corpus, cfg, None if prims is None else prims.to(corpus.device))  # (B, R)
    both = (warp_depth < cfg.horizon) & (ours < cfg.horizon)
    if moving:  # the rays the obstacles stop short, and how far Warp's boxes are from the primitives there
        blocked = ours < tracer_depth(corpus, cfg) - 1e-3  # (B, R)
        result["obstacle_rays"] = int(blocked.sum())
        result["obstacle_median_abs_depth_diff_m"] = (
            float(np.median(np.abs(warp_depth[blocked] - ours[blocked]))) if blocked.any() else None
        )
    return result | {
        "median_abs_depth_diff_m": float(np.median(np.abs(warp_depth[both] - ours[both])))
        if both.any()
        else None,
        "hit_disagreement": float(((warp_depth < cfg.horizon) != (ours < cfg.horizon)).mean()),
    }
