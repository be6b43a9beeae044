"""`navi bench freespace`: each scene of a corpus as free space at the drone's radius (its voxels, its
connected parts, a geodesic field from a spawn), timed and sized, and the coverage its spawns can reach
in the evaluation's episodes, per 1,000 steps: an upper bound from the drone's speed limit and the free
space of the spawn's part, and what a planner with the map flies under the env's speed limits and
proximity limiter (navi_env.space.freespace.greedy_coverage), with the reward per step the env would pay
that flight (flight_reward), and how open the first spawn's part is: the view clearance (the shortest
ray of the 256 x 48 view, as the env reads it) at OPEN_POINTS of its voxels, its median and the share of
them at the cap (EnvConfig.clearance_range, 10 m), where the rewards and the limiter read only "open".
With goals G > 0 it also builds the scene's point-goal table (navi_env.space.goal_tables: G goals 5-30 m
from the spawns, their geodesic fields), timed and sized."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from navi_env.config import EnvConfig
from navi_env.corpus.folder import load_corpus_folder
from navi_env.rays import spherical_directions
from navi_env.sim.rewards import escape_potential, exploration_term, proximity_term
from navi_env.space.freespace import (
    Flight,
    FreeSpace,
    components,
    coverage_bound,
    free_space,
    geodesic,
    greedy_coverage,
    lattice_cell,
    reachable_cells,
)
from navi_env.space.goal_tables import goal_table
from navi_env.tracer.scene import SceneCorpus
from navi_env.tracer.trace import trace

PLANNER_SPAWNS = 3
"""Spawns per scene the planner flies from (the median is reported)."""
OPEN_POINTS = 64
"""Voxels of the spawn's part (drawn with a fixed seed) whose view clearance gives the part's openness."""


def view_clearance(
    corpus: SceneCorpus,
    scene: int,
    space: FreeSpace,
    labels: torch.Tensor,
    start: torch.Tensor,
    cfg: EnvConfig,
) -> torch.Tensor:
    """The view clearance (P,) meters, capped at cfg.clearance_range, at up to OPEN_POINTS voxel centres
    of the part holding voxel start (1, 3); empty when that voxel is blocked."""
    part = labels[tuple(start[0].tolist())]  # () the part's label, -1 when blocked
    if int(part) < 0:
        return torch.empty(0)
    index = torch.nonzero(labels == part)  # (M, 3) int64
    pick = torch.randperm(index.shape[0], generator=torch.Generator().manual_seed(0))[:OPEN_POINTS]  # (P,)
    origins = space.centre_of(index[pick.to(index.device)]).contiguous()  # (P, 3)
    dirs = spherical_directions(cfg.azimuth_bins, cfg.elevation_bins, corpus.device)  # (R, 3)
    ids = torch.full((origins.shape[0],), scene, dtype=torch.int64, device=corpus.device)  # (P,)
    depth = torch.empty(origins.shape[0], dirs.shape[0], device=corpus.device)  # (P, R) meters
    trace(
        corpus,
        ids,
        origins,
        dirs,
        out_depth=depth,
        horizon=cfg.clearance_range,
        hit_epsilon=cfg.hit_epsilon,
        hit_slope=cfg.hit_slope,
    )
    return depth.min(dim=1).values.clamp(max=cfg.clearance_range).cpu()  # (P,)


def limiter(cfg: EnvConfig) -> Callable[[float], float]:
    """The env's proximity speed limiter (navi_env.sim.physics.limiter_scale) as a function of the
    clearance in meters, capped at clearance_range as the env caps the view clearance."""

    def scale(clearance: float) -> float:
        span = cfg.limiter_distance - cfg.drone_radius
        ramp = (min(clearance, cfg.clearance_range) - cfg.drone_radius) / span
        return min(1.0, max(cfg.limiter_min_fraction, ramp))

    return scale


def flight_reward(flight: Flight, steps: int, cfg: EnvConfig) -> float:
    """The reward per step the env would pay a planner's flight over an episode of `steps` steps, from the
    env's own terms at each move's end (its distance to the nearest surface standing in for the view's
    clearance): the existential tax, the proximity cost and the escape shaping's drain ((gamma - 1) Phi per
    step; Phi(end) - Phi(start) is left out) for every step the move takes, the exploration bonus once per
    new cell; a flight that ends early (its part covered) hovers at its last clearance for the rest.
    Foraging and structure read the view, which the lattice does not have, and are left out; the planner
    flies free voxels, so it never collides."""
    r, step = cfg.reward, cfg.max_speed * cfg.dt
    moves = flight.moves or [(0.0, cfg.clearance_range, False)]
    seconds = torch.tensor([m[0] for m in moves], dtype=torch.float64)  # (M,)
    clear = torch.tensor([m[1] for m in moves], dtype=torch.float64).clamp(max=cfg.clearance_range)  # (M,)
    new = torch.tensor([m[2] for m in moves])  # (M,) bool
    n = seconds / cfg.dt  # (M,) env steps each move takes
    n[-1] += max(steps - float(n.sum()), 0.0)  # the rest of the episode at the last clearance
    per_step = (
        r.existential_tax
        + proximity_term(clear, r)
        + (r.shaping_gamma - 1.0) * escape_potential(clear, step, r)
    )
    total = (n * per_step).sum() + exploration_term(new, clear, r).sum()  # () float64
    return float(total) / steps


def survey_scene(
    corpus: SceneCorpus,
    scene: int,
    spawns: torch.Tensor,
    cell: float,
    radius: float,
    episode_steps: int,
    goals: int = 0,
    cfg: EnvConfig | None = None,
) -> dict[str, Any]:
    """One scene's row (see the module docstring); spawns (K, 3) world meters; cfg the env's (default
    EnvConfig(): its limits fly the planner, its reward scores the planner's flight)."""
    cfg = EnvConfig() if cfg is None else cfg
    sync = torch.cuda.synchronize if corpus.device.type == "cuda" else (lambda: None)
    cell = lattice_cell(corpus, scene, cell)  # coarser for a map whose bounds span hundreds of meters
    t0 = time.perf_counter()
    space = free_space(corpus, scene, cell, radius)
    sync()
    t1 = time.perf_counter()
    labels = components(space.free, space.edges)
    sync()
    t2 = time.perf_counter()
    spawns = spawns.to(corpus.device)
    start = space.voxel(spawns[:1])  # (1, 3)
    field = (
        geodesic(space.free, start, cell, space.edges) if bool(space.free[tuple(start[0].tolist())]) else None
    )
    sync()
    t3 = time.perf_counter()
    reach = [reachable_cells(space, labels, p) for p in spawns[:8]]
    t4 = time.perf_counter()
    flights = [
        greedy_coverage(space, p, episode_steps * cfg.dt, limiter(cfg), cfg.max_speed, cfg.max_vertical_speed)
        for p in spawns[:PLANNER_SPAWNS]
    ]
    t5 = time.perf_counter()
    table = goal_table(space, spawns, count=goals) if goals > 0 else None  # point goals 5-30 m away
    sync()
    t6 = time.perf_counter()
    parts = labels[labels >= 0].unique()  # (P,) the part labels, sorted
    sizes = torch.bincount(torch.searchsorted(parts, labels[labels >= 0]))  # (P,) voxels per part
    finite = field[torch.isfinite(field)] if field is not None else torch.empty(0)
    reachable = int(statistics.median(reach))
    view = view_clearance(corpus, scene, space, labels, start, cfg)  # (P,) meters
    return {
        "name": corpus.infos[scene].name,
        "cell_m": cell,
        "grid": list(space.free.shape),
        "free_share": round(float(space.free.float().mean()), 4),
        "parts": int(parts.numel()),
        "largest_part_share": round(float(sizes.max()) / max(int(space.free.sum()), 1), 4)
        if parts.numel()
        else 0.0,
        "reachable_cells_median": reachable,
        "coverage_bound_per_1k": round(coverage_bound(reachable, episode_steps, cfg.max_speed * cfg.dt), 1),
        "planner_coverage_per_1k": round(
            statistics.median(1000.0 * f.cells / episode_steps for f in flights), 1
        ),
        "planner_speed_m_s": round(statistics.median(f.meters / max(f.seconds, 1e-9) for f in flights), 2),
        "planner_reward_per_step": round(
            statistics.median(flight_reward(f, episode_steps, cfg) for f in flights), 4
        ),
        "farthest_path_m": round(float(finite.max()), 2) if finite.numel() else None,
        "view_clearance_median_m": round(float(view.median()), 2) if view.numel() else None,
        "open_share": round(float((view >= cfg.clearance_range).float().mean()), 4) if view.numel() else 0.0,
        "seconds": {
            "sample": round(t1 - t0, 3),
            "components": round(t2 - t1, 3),
            "geodesic": round(t3 - t2, 3),
            "planner": round(t5 - t4, 3),
            "goals": round(t6 - t5, 3),
        },
        "goals": table.goals.shape[0] if table is not None else 0,
        "goal_pairs_per_spawn": round(float(table.pairs.sum(dim=1).float().mean()), 2)
        if table is not None
        else 0.0,
        "goal_bytes": table.nbytes() if table is not None else 0,
        "grid_bytes": space.free.numel()
        * (1 + 4 + 8 + 4 + 13),  # free, clearance, labels, one geodesic field, edges
    }


def survey_corpus(
    corpus_dir: Path,
    device: str,
    cell: float = 0.5,
    radius: float | None = None,
    episode_steps: int = 500,
    goals: int = 0,
    reward: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """Every scene of the corpus folder (radius: the env's drone radius unless given); `reward` replaces
    RewardConfig fields for the planner's reward per step."""
    cfg = EnvConfig()
    weights: dict[str, Any] = dict(reward or {})  # float fields, checked by the caller
    cfg = replace(cfg, reward=replace(cfg.reward, **weights))
    radius = cfg.drone_radius if radius is None else radius
    scenes, manifest = load_corpus_folder(corpus_dir, torch.device(device))
    spawns = manifest.spawn_tensors()
    rows = [
        survey_scene(scenes, s, spawns[s], cell, radius, episode_steps, goals, cfg)
        for s in range(len(scenes))
    ]
    return {
        "corpus": str(corpus_dir),
        "device": str(scenes.device),
        "cell_m": cell,
        "radius_m": radius,
        "episode_steps": episode_steps,
        "step_m": cfg.max_speed * cfg.dt,
        "scenes": rows,
        "coverage_bound_per_1k_min": min(r["coverage_bound_per_1k"] for r in rows),
        "planner_coverage_per_1k_min": min(r["planner_coverage_per_1k"] for r in rows),
    }
