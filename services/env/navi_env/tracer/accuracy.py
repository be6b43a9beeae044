"""Tracer accuracy against an exact triangle-mesh ray cast (Moller-Trumbore over every triangle).

`openarena_accuracy` compiles a Quake 3 map with the compiler, traces rays from its spawn points and
compares with the exact first hit on the map's drawn triangles, over rays whose exact hit lies
inside the scene cube. Brute force over (ray, triangle) pairs in chunks: fine on a GPU, tens of
seconds on a CPU for a few thousand rays.

Shapes: P rays, F triangles, B agents, R rays per agent.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from navi_env.rays import spherical_directions
from navi_env.tracer.scene import SceneCorpus, load_scene
from navi_env.tracer.trace import trace

PAIRS_PER_CHUNK = 1 << 21  # (ray, triangle) pairs evaluated at once


@dataclass(frozen=True)
class AccuracyReport:
    """Traced vs exact depth over one set of rays."""

    rays: int  # rays compared
    exact_hits: int  # rays whose exact first hit lies inside the cube
    hit_disagreement: float  # share of rays where traced hit/miss != exact hit/miss
    median_error_voxels: float  # median |traced - exact| over rays both call hits
    p95_error_voxels: float  # 95th percentile of the same
    voxel_size: float  # meters
    resolution: int


def mesh_hits(origins: torch.Tensor, dirs: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Exact first-hit distance (P,) float64 of rays origins, dirs (P, 3) against triangles (F, 3, 3).

    inf on a miss; all math in float64 on the tensors' device.
    """
    o, d, tri = origins.double(), dirs.double(), triangles.double()
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]  # (F, 3) each
    out = torch.full((len(o),), float("inf"), dtype=torch.float64, device=o.device)  # (P,)
    step = max(1, PAIRS_PER_CHUNK // max(1, len(tri)))
    for i in range(0, len(o), step):
        oc, dc = o[i : i + step, None, :], d[i : i + step, None, :]  # (C, 1, 3) each
        h = torch.linalg.cross(dc.expand(-1, len(tri), -1), e2[None].expand(len(oc), -1, -1))  # (C, F, 3)
        det = (e1[None] * h).sum(-1)  # (C, F)
        ok = det.abs() > 1e-12
        inv = torch.where(
            ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det)
        )  # (C, F)
        s = oc - a[None]  # (C, F, 3)
        u = (s * h).sum(-1) * inv  # (C, F)
        q = torch.linalg.cross(s, e1[None].expand(len(oc), -1, -1))  # (C, F, 3)
        v = (dc * q).sum(-1) * inv  # (C, F)
        t = (e2[None] * q).sum(-1) * inv  # (C, F)
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)  # (C, F)
        out[i : i + step] = torch.where(hit, t, torch.full_like(t, float("inf"))).min(dim=1).values
    return out


def compare(
    depth: np.ndarray, exact: np.ndarray, horizon: float, voxel: float, resolution: int
) -> AccuracyReport:
    """depth (P,) traced meters (horizon on a miss), exact (P,) meters (inf on a miss)."""
    traced_hit = depth < horizon
    exact_hit = np.isfinite(exact)
    both = traced_hit & exact_hit
    err = np.abs(depth[both] - exact[both]) / voxel  # voxels
    return AccuracyReport(
        rays=len(depth),
        exact_hits=int(exact_hit.sum()),
        hit_disagreement=float((traced_hit != exact_hit).mean()),
        median_error_voxels=float(np.median(err)) if len(err) else float("nan"),
        p95_error_voxels=float(np.quantile(err, 0.95)) if len(err) else float("nan"),
        voxel_size=voxel,
        resolution=resolution,
    )


def scene_accuracy(
    corpus: SceneCorpus,
    triangles: np.ndarray,
    agents: int,
    rays_az: int,
    rays_el: int,
    horizon: float = 1000.0,
) -> AccuracyReport:
    """Trace from scene 0's spawns (cycled) with a spherical pattern; compare with triangles (F, 3, 3)."""
    info = corpus.infos[0]
    if len(info.spawns) == 0:
        raise ValueError(f"scene {info.name} has no spawn points to trace from")
    dev = corpus.device
    spawns = torch.from_numpy(info.spawns)[torch.arange(agents) % len(info.spawns)]  # (B, 3) float32
    spawns = spawns + 0.01 * torch.arange(agents, dtype=torch.float32)[:, None] / agents  # (B, 3) distinct
    dirs = spherical_directions(rays_az, rays_el)  # (R, 3)
    depth = torch.empty(agents, len(dirs), device=dev)  # (B, R) float32
    trace(corpus, torch.zeros(agents, dtype=torch.int64, device=dev), spawns.to(dev), dirs.to(dev),
          out_depth=depth, horizon=horizon, max_steps=2048)  # fmt: skip
    o = spawns[:, None, :].expand(-1, len(dirs), -1).reshape(-1, 3)  # (P, 3)
    d = dirs[None].expand(agents, -1, -1).reshape(-1, 3)  # (P, 3)
    exact = mesh_hits(o.to(dev), d.to(dev), torch.from_numpy(triangles).to(dev)).cpu().numpy()  # (P,)
    ends = (
        o.double().numpy() + np.where(np.isfinite(exact), exact, 0.0)[:, None] * d.double().numpy()
    )  # (P, 3)
    in_cube = ((ends >= info.cube_min) & (ends <= info.cube_max)).all(axis=1)
    exact = np.where(in_cube & (exact <= horizon), exact, np.inf)
    return compare(depth.cpu().numpy().reshape(-1), exact, horizon, info.voxel_size, info.resolution)


def openarena_accuracy(
    pk3: str | os.PathLike[str],
    map_name: str,
    resolution: int,
    agents: int = 16,
    rays_az: int = 64,
    rays_el: int = 32,
    device: str = "cpu",
) -> AccuracyReport:
    """Compile `map_name` from the pk3 at `resolution` and measure the tracer against its triangles."""
    from navi_compiler.compile import compile_scene
    from navi_compiler.ingest import load_scene as load_source

    scene = load_source(pk3, map_name=map_name)
    gmdag, _ = compile_scene(scene, resolution=resolution)
    triangles = scene.vertices[scene.faces]  # (F, 3, 3) meters
    return scene_accuracy(load_scene(gmdag, device), triangles, agents, rays_az, rays_el)
