"""`navi bench trace`: rays per second of `trace` with the 256x48 spherical pattern.

Agents stand at the scene's spawn points (cycled, random yaw) or, without spawns, at random points
with clearance; every agent casts the same body-frame pattern rotated by its yaw inside the kernel.
Timing: CUDA events around `launches` back-to-back launches after warm-up (perf_counter on the CPU).
Steps per ray come from one extra launch with the step counter on. `bench_trace_maps` runs the same
measurement on every scene file of a folder, one at a time, and summarises the rates, steps and bytes
(min / median / max, and how many maps miss the rate and memory targets).

Shapes: B agents, R = Az * El rays per agent.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from navi_env.config import EnvConfig
from navi_env.rays import spherical_directions, tiled_ray_order
from navi_env.tracer import primitives as obstacles
from navi_env.tracer.scene import SceneCorpus, load_scene
from navi_env.tracer.trace import DEFAULT_HORIZON, DEFAULT_MAX_STEPS, sample_distance, trace


@dataclass(frozen=True)
class TraceBenchConfig:
    """What `bench_trace` measures."""

    agents: int = 4096  # B
    device: str = "cuda"  # "cpu" or "cuda[:N]"
    launches: int = 20  # timed launches
    warmup: int = 3  # untimed launches first
    azimuth_bins: int = 256  # Az
    elevation_bins: int = 48  # El
    max_steps: int = DEFAULT_MAX_STEPS
    horizon: float = DEFAULT_HORIZON  # meters
    clearance_voxels: float = 2.0  # minimum clearance of random agent positions
    seed: int = 0
    obstacles: int = (
        0  # K dynamic primitives per agent (navi_env.tracer.primitives.scatter), moved every launch
    )
    hit_slope: float = EnvConfig.hit_slope  # the hit threshold's growth with distance, as the env traces


@dataclass(frozen=True)
class TraceBenchResult:
    """One benchmark measurement (printed as JSON by `navi bench trace --json`)."""

    device: str  # GPU name or "cpu (n threads)"
    scene: str
    resolution: int
    agents: int  # B
    rays_per_agent: int  # R
    pattern: tuple[int, int]  # (Az, El)
    launches: int
    ms_per_launch: float
    grays_per_s: float  # 1e9 rays per second
    observations_per_s: float  # agents x launches per second
    mean_steps: float  # main-loop steps per ray
    p99_steps: float
    warp_steps: float  # per ray, the steps of the longest ray of its warp (32 rays in the launch's order)
    warp_efficiency: float  # mean_steps / warp_steps: the share of a warp's step slots that do work
    hit_fraction: float
    ray_order: str  # "tiled 16x2": the schedule the rays ran in
    bytes_per_scene: int
    max_steps: int
    horizon_m: float
    obstacles_per_agent: int = 0  # K
    obstacle_hit_fraction: float = 0.0  # rays whose hit is a primitive
    hit_slope: float = 0.0  # the threshold 0.1 voxel + hit_slope * t


@dataclass(frozen=True)
class Agents:
    """Agent placement for a benchmark."""

    scene_ids: torch.Tensor  # (B,) int64
    origins: torch.Tensor  # (B, 3) float32 meters
    yaw: torch.Tensor  # (B,) float32 radians


def place_agents(corpus: SceneCorpus, count: int, clearance_voxels: float, seed: int) -> Agents:
    """Agents of scene 0 at its spawns (cycled) or at random free points; random yaw."""
    info = corpus.infos[0]
    gen = torch.Generator().manual_seed(seed)
    if len(info.spawns) > 0:
        idx = torch.arange(count) % len(info.spawns)  # (B,)
        origins = torch.from_numpy(info.spawns)[idx]  # (B, 3) float32
    else:
        origins = free_positions(corpus, count, clearance_voxels * info.voxel_size, gen)  # (B, 3)
    yaw = torch.rand(count, generator=gen) * (2 * math.pi)  # (B,)
    dev = corpus.device
    return Agents(
        scene_ids=torch.zeros(count, dtype=torch.int64, device=dev),
        origins=origins.to(dev),
        yaw=yaw.to(dev),
    )


def free_positions(corpus: SceneCorpus, count: int, clearance: float, gen: torch.Generator) -> torch.Tensor:
    """(count, 3) float32 points of scene 0 with sample_distance >= clearance (meters), on the CPU."""
    info = corpus.infos[0]
    lo = torch.tensor(info.bounds_min, dtype=torch.float32)  # (3,)
    hi = torch.tensor(info.bounds_max, dtype=torch.float32)  # (3,)
    found: list[torch.Tensor] = []
    total = 0
    for _ in range(200):
        p = lo + torch.rand(8 * count, 3, generator=gen) * (hi - lo)  # (8C, 3)
        ids = torch.zeros(len(p), dtype=torch.int64, device=corpus.device)  # (8C,)
        d = sample_distance(corpus, ids, p.to(corpus.device)).cpu()  # (8C,)
        keep = p[d >= clearance]  # (K, 3)
        found.append(keep)
        total += len(keep)
        if total >= count:
            return torch.cat(found)[:count]
    raise ValueError(f"scene {info.name}: found only {total} free points with clearance {clearance:.3g} m")


WARP = 32
"""Rays side by side in one GPU warp (consecutive work items of a launch)."""


def warp_steps(steps: torch.Tensor, order: torch.Tensor | None) -> float:
    """Mean over rays of the step count of the longest ray in its warp: steps (B, R) int32 per ray in
    pattern order; order (R,) the launch's ray order (work item j traces ray order[j]) or None. A warp
    takes as many steps as its longest ray, so mean_steps / warp_steps is the share of lane-steps that
    trace (1: every ray of every warp equally long). A last partial warp counts its own rays only."""
    s = (steps if order is None else steps[:, order.long()]).float()  # (B, R) in launch order
    b, r = s.shape
    full = r // WARP * WARP
    longest = s[:, :full].view(b, -1, WARP).amax(-1) * WARP  # (B, R // 32): longest x rays of the warp
    total = longest.sum() + (s[:, full:].amax(-1).sum() * (r - full) if full < r else 0.0)
    return float(total) / (b * r)


def warp_steps_ref(steps: torch.Tensor, order: torch.Tensor | None) -> float:
    """Slow twin of warp_steps: each ray, one at a time, charged its warp's longest ray."""
    b, r = steps.shape
    total = 0.0
    for actor in range(b):
        items = [int(order[j]) if order is not None else j for j in range(r)]
        for j in range(r):
            start = j // WARP * WARP
            total += max(int(steps[actor, k]) for k in items[start : min(start + WARP, r)])
    return total / (b * r)


def _time_launches(fn: object, device: torch.device, launches: int) -> float:
    """Seconds per launch of fn() averaged over `launches` back-to-back calls."""
    if device.type == "cuda":
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for _ in range(launches):
            fn()  # type: ignore[operator]
        end.record()
        end.synchronize()
        return start.elapsed_time(end) / 1000.0 / launches
    t0 = time.perf_counter()
    for _ in range(launches):
        fn()  # type: ignore[operator]
    return (time.perf_counter() - t0) / launches


def bench_trace(corpus: SceneCorpus, cfg: TraceBenchConfig) -> TraceBenchResult:
    """Measure trace on scene 0 of `corpus`; returns the JSON-ready result."""
    dev = corpus.device
    agents = place_agents(corpus, cfg.agents, cfg.clearance_voxels, cfg.seed)
    dirs = spherical_directions(cfg.azimuth_bins, cfg.elevation_bins, dev)  # (R, 3)
    order = tiled_ray_order(cfg.azimuth_bins, cfg.elevation_bins).to(dev)  # (R,) 16x2 tiles per warp
    b, r = cfg.agents, len(dirs)
    depth = torch.empty(b, r, device=dev)  # (B, R) float32
    semantic = torch.empty(b, r, dtype=torch.uint8, device=dev)  # (B, R) uint8
    steps = torch.empty(b, r, dtype=torch.int32, device=dev)  # (B, R) int32
    prims = obstacles.scatter(agents.origins, cfg.obstacles, torch.Generator().manual_seed(cfg.seed + 1))
    centers = prims[:, :, obstacles.CENTER : obstacles.CENTER + 3]  # (B, K, 3) view, moved in place
    drift = torch.full_like(centers, 0.01)  # (B, K, 3) meters per launch, back and forth
    moving = cfg.obstacles > 0
    prims_or_none = prims if moving else None

    def launch() -> None:
        if moving:
            centers.add_(drift)
            drift.neg_()
        trace(corpus, agents.scene_ids, agents.origins, dirs, yaw=agents.yaw, out_depth=depth,
              out_semantic=semantic, ray_order=order, max_steps=cfg.max_steps, horizon=cfg.horizon,
              skip_direction_validation=True, prims=prims_or_none, hit_slope=cfg.hit_slope)  # fmt: skip

    trace(corpus, agents.scene_ids, agents.origins, dirs, yaw=agents.yaw, out_depth=depth, out_semantic=semantic,
          out_steps=steps, ray_order=order, max_steps=cfg.max_steps, horizon=cfg.horizon, prims=prims_or_none,
          hit_slope=cfg.hit_slope)  # fmt: skip
    obstacle_hits = float((semantic == obstacles.OBSTACLE_CLASS + 1).float().mean()) if moving else 0.0
    step_counts = steps.flatten().float()  # (B*R,)
    per_warp = warp_steps(steps, order)
    for _ in range(cfg.warmup):
        launch()
    seconds = _time_launches(launch, dev, cfg.launches)
    info = corpus.infos[0]
    device = (
        torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"cpu ({torch.get_num_threads()} threads)"
    )
    sampled = step_counts[:: max(1, len(step_counts) // 1_000_000)]  # (<= ~1M,) for the quantile
    return TraceBenchResult(
        device=device,
        scene=info.name,
        resolution=info.resolution,
        agents=b,
        rays_per_agent=r,
        pattern=(cfg.azimuth_bins, cfg.elevation_bins),
        launches=cfg.launches,
        ms_per_launch=seconds * 1e3,
        grays_per_s=b * r / seconds / 1e9,
        observations_per_s=b / seconds,
        mean_steps=float(step_counts.mean()),
        p99_steps=float(torch.quantile(sampled, 0.99)),
        warp_steps=per_warp,
        warp_efficiency=float(step_counts.mean()) / per_warp if per_warp > 0 else 1.0,
        hit_fraction=float((semantic > 0).float().mean()),
        ray_order="tiled 16x2",
        bytes_per_scene=info.nbytes,
        max_steps=cfg.max_steps,
        horizon_m=cfg.horizon,
        obstacles_per_agent=cfg.obstacles,
        obstacle_hit_fraction=obstacle_hits,
        hit_slope=cfg.hit_slope,
    )


TARGET_GRAYS = 10.0
"""G rays/s every map should reach on one H100 (docs/PERFORMANCE.md, targets)."""
TARGET_DENSE_RATIO = 100.0
"""How many times smaller than a dense float32 grid a map is asked to be on the device (a reported
figure; docs/PERFORMANCE.md says why dense float32 is not the yardstick)."""


def dense_bytes(resolution: int) -> int:
    """Bytes of a dense float32 grid of resolution^3 cells (512^3: 512 MiB)."""
    return 4 * resolution**3


def bench_trace_maps(
    paths: list[Path],
    cfg: TraceBenchConfig,
    say: Callable[[str], None],
    extra: Callable[[SceneCorpus, TraceBenchResult], dict[str, object]] | None = None,
) -> dict[str, object]:
    """bench_trace on each scene file (loaded alone, freed before the next); `say` gets a line per map.
    `extra(corpus, result)` adds keys to a map's row (an anchor measured on the same map in the same job).
    Returns {"maps": [each result plus dense_ratio], "summary": summarise_maps(...)}."""
    if not paths:
        raise ValueError("no .gmdag files to measure")
    rows: list[dict[str, object]] = []
    for i, path in enumerate(paths):
        corpus = load_scene(path, cfg.device)
        r = bench_trace(corpus, cfg)
        row = asdict(r) | {"dense_ratio": dense_bytes(r.resolution) / r.bytes_per_scene}
        if extra is not None:
            row |= extra(corpus, r)
        rows.append(row)
        say(
            f"[{i + 1}/{len(paths)}] {r.scene}: {r.grays_per_s:.2f} G rays/s, {r.mean_steps:.1f} mean / "
            f"{r.p99_steps:.0f} p99 / {r.warp_steps:.1f} warp steps, {r.bytes_per_scene / 1e6:.1f} MB "
            f"({row['dense_ratio']:.0f}x dense)"
        )
        del corpus
        if torch.device(cfg.device).type == "cuda":
            torch.cuda.empty_cache()
    return {"maps": rows, "summary": summarise_maps(rows)}


def summarise_maps(rows: list[dict[str, object]]) -> dict[str, object]:
    """Min / median / max over maps of the rate, the steps per ray and the device bytes (with the maps
    at the extremes), and the maps below TARGET_GRAYS and TARGET_DENSE_RATIO."""

    def spread(key: str) -> dict[str, object]:
        values = [float(r[key]) for r in rows]  # type: ignore[arg-type]
        lo, hi = min(range(len(rows)), key=values.__getitem__), max(range(len(rows)), key=values.__getitem__)
        return {
            "min": values[lo],
            "min_scene": rows[lo]["scene"],
            "median": statistics.median(values),
            "max": values[hi],
            "max_scene": rows[hi]["scene"],
        }

    def below(key: str, target: float) -> list[object]:
        return [r["scene"] for r in rows if float(r[key]) < target]  # type: ignore[arg-type]

    return {
        "maps": len(rows),
        "grays_per_s": spread("grays_per_s"),
        "mean_steps": spread("mean_steps"),
        "p99_steps": spread("p99_steps"),
        "warp_efficiency": spread("warp_efficiency"),
        "bytes_per_scene": spread("bytes_per_scene"),
        "dense_ratio": spread("dense_ratio"),
        "below_target_grays": below("grays_per_s", TARGET_GRAYS),
        "below_target_dense_ratio": below("dense_ratio", TARGET_DENSE_RATIO),
        "targets": {"grays_per_s": TARGET_GRAYS, "dense_ratio": TARGET_DENSE_RATIO},
    }


def rays_for_warp(corpus: SceneCorpus, cfg: TraceBenchConfig) -> tuple[np.ndarray, np.ndarray]:
    """The benchmark's world-space rays: origins (B*R, 3) and directions (B*R, 3) float32, on the host."""
    agents = place_agents(corpus, cfg.agents, cfg.clearance_voxels, cfg.seed)
    dirs = spherical_directions(cfg.azimuth_bins, cfg.elevation_bins)  # (R, 3)
    yaw = agents.yaw.cpu()  # (B,)
    c, s = torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]  # (B, 1)
    x, y, z = dirs[None, :, 0], dirs[None, :, 1], dirs[None, :, 2]  # (1, R)
    world = torch.stack([c * x - s * y, s * x + c * y, z.expand(len(yaw), -1)], dim=-1)  # (B, R, 3)
    origins = agents.origins.cpu()[:, None, :].expand(-1, len(dirs), -1)  # (B, R, 3)
    return origins.reshape(-1, 3).numpy().copy(), world.reshape(-1, 3).numpy().copy()


def tracer_depth(corpus: SceneCorpus, cfg: TraceBenchConfig, prims: torch.Tensor | None = None) -> np.ndarray:
    """(B, R) tracer depth for the benchmark's agents, on the host, traced as `bench_trace` traces them
    (its hit threshold slope; the ray order changes no result): what the anchors are compared with.
    `prims` (B, K, 16): each agent's own dynamic primitives, traced with the scene."""
    agents = place_agents(corpus, cfg.agents, cfg.clearance_voxels, cfg.seed)
    pattern = spherical_directions(cfg.azimuth_bins, cfg.elevation_bins, corpus.device)  # (R, 3)
    depth = torch.empty(cfg.agents, len(pattern), device=corpus.device)  # (B, R) float32
    trace(corpus, agents.scene_ids, agents.origins, pattern, yaw=agents.yaw, out_depth=depth,
          max_steps=cfg.max_steps, horizon=cfg.horizon, hit_slope=cfg.hit_slope, prims=prims)  # fmt: skip
    return depth.cpu().numpy()
