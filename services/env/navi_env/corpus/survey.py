"""`navi bench freespace`: each scene of a corpus as free space at the drone's radius (its voxels, its
connected parts, a geodesic field from a spawn), timed and sized, and the coverage its spawns can reach:
an upper bound on the evaluation's coverage per 1,000 steps from the drone's speed limit and the free
space of the spawn's part (navi_env.corpus.freespace)."""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import torch

from navi_env.corpus.folder import load_corpus
from navi_env.corpus.freespace import components, coverage_bound, free_space, geodesic, reachable_cells
from navi_env.sim.config import EnvConfig


def survey_scene(
    corpus: Any,
    scene: int,
    spawns: torch.Tensor,
    cell: float,
    radius: float,
    episode_steps: int,
    step_m: float,
) -> dict[str, Any]:
    """One scene's row (see the module docstring); spawns (K, 3) world meters."""
    sync = torch.cuda.synchronize if corpus.device.type == "cuda" else (lambda: None)
    t0 = time.perf_counter()
    space = free_space(corpus, scene, cell, radius)
    sync()
    t1 = time.perf_counter()
    labels = components(space.free)
    sync()
    t2 = time.perf_counter()
    spawns = spawns.to(corpus.device)
    start = space.voxel(spawns[:1])  # (1, 3)
    field = geodesic(space.free, start, cell) if bool(space.free[tuple(start[0].tolist())]) else None
    sync()
    t3 = time.perf_counter()
    reach = [reachable_cells(space, labels, p) for p in spawns[:8]]
    parts = labels[labels >= 0].unique()
    finite = field[torch.isfinite(field)] if field is not None else torch.empty(0)
    return {
        "name": corpus.infos[scene].name,
        "grid": list(space.free.shape),
        "free_share": round(float(space.free.float().mean()), 4),
        "parts": int(parts.numel()),
        "largest_part_share": round(
            float(torch.bincount(torch.searchsorted(parts, labels[labels >= 0])).max() / space.free.sum()), 4
        ),
        "reachable_cells_median": statistics.median(reach) if reach else 0,
        "coverage_bound_per_1k": round(
            coverage_bound(int(statistics.median(reach)), episode_steps, step_m), 1
        )
        if reach
        else 0.0,
        "farthest_path_m": round(float(finite.max()), 2) if finite.numel() else None,
        "seconds": {
            "sample": round(t1 - t0, 3),
            "components": round(t2 - t1, 3),
            "geodesic": round(t3 - t2, 3),
        },
        "grid_bytes": space.free.numel() * (1 + 4 + 8 + 4),  # free, clearance, labels, one geodesic field
    }


def survey_corpus(
    corpus_dir: Path, device: str, cell: float = 0.5, radius: float | None = None, episode_steps: int = 500
) -> dict[str, Any]:
    """Every scene of the corpus folder; the drone's radius and step length from EnvConfig's defaults."""
    cfg = EnvConfig()
    radius = cfg.drone_radius if radius is None else radius
    step_m = cfg.max_speed * cfg.dt
    scenes, manifest = load_corpus(corpus_dir, torch.device(device))
    spawns = manifest.spawn_tensors()
    rows = [
        survey_scene(scenes, s, spawns[s], cell, radius, episode_steps, step_m) for s in range(len(scenes))
    ]
    return {
        "corpus": str(corpus_dir),
        "device": str(scenes.device),
        "cell_m": cell,
        "radius_m": radius,
        "episode_steps": episode_steps,
        "step_m": step_m,
        "scenes": rows,
        "coverage_bound_per_1k_min": min(r["coverage_bound_per_1k"] for r in rows),
    }
