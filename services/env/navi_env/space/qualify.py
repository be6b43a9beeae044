"""Spawn qualification: probe a grid of candidate positions and keep those with a useful view.

A scene's candidates are a 5 x 7 x 5 grid (x, y, z) over its geometry bounds, cell-centred, plus the
spawn points stored in the .gmdag. Each candidate casts a 48 x 12 full-sphere pattern; it is *free*
when it lies on the free side of the field and its clearance (the shortest of those rays, as the env
measures clearance) is at least `min_clearance`. A candidate's profile is the fraction
of rays that miss (starvation) and the fraction closer than `near_distance`. A candidate is *viable*
when it is free, its starvation is below `max_starvation` and its near fraction below `max_near`;
viable candidates are ranked by score = (1 - starvation) * (1 - near) * min(clearance / 2 m, 1).
The scene fails with no viable candidate or when its best (lowest) starvation is >= max_starvation.

A passing scene also records its trace cost: the mean sphere-tracing steps per ray of the same
pattern cast from its best spawns with the env's hit threshold and step cap. The tracer's time per
ray follows its mean steps per ray, so data-parallel ranks share the scenes out by it
(corpus.folder.load_corpus_folder).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch

from navi_env.config import EnvConfig, SensorConfig
from navi_env.rays import ray_pattern
from navi_env.tracer.scene import SceneCorpus
from navi_env.tracer.trace import sample_distance, trace


@dataclass(frozen=True)
class QualifyConfig:
    """Thresholds of spawn qualification."""

    grid: tuple[int, int, int] = (5, 7, 5)
    """Candidates per axis (x, y, z) over the scene bounds."""
    azimuth_bins: int = 48
    """Azimuth bins of the probe pattern."""
    elevation_bins: int = 12
    """Elevation bins of the probe pattern (full sphere)."""
    horizon: float = 100.0
    """Probe ray range, meters."""
    min_clearance: float = 0.75
    """A candidate is free when its clearance is at least this, meters."""
    max_starvation: float = 0.7
    """Viable candidates see fewer misses than this fraction; the scene fails when none does."""
    near_distance: float = 0.5
    """Rays shorter than this (m) count as near field."""
    max_near: float = 0.5
    """Viable candidates have fewer near-field rays than this fraction."""
    trace_max_steps: int = 256
    """Sphere-tracing iteration cap per probe ray."""
    cost_spawns: int = 64
    """The trace cost is measured from this many of the best spawns."""


@dataclass(frozen=True)
class Qualification:
    """The verdict on one scene."""

    verdict: str  # "pass" or "fail"
    reason: str  # one line: why it failed, or a summary when it passed
    candidates: int  # grid plus file spawn candidates probed
    free_candidates: int  # candidates with clearance >= min_clearance
    viable_spawns: int  # free candidates with an acceptable view
    best_starvation: float  # lowest miss fraction over free candidates (1.0 when none is free)
    spawns: list[list[float]] = field(default_factory=list)  # viable positions (meters), best first
    scores: list[float] = field(default_factory=list)  # their scores, same order
    trace_cost: float = 0.0  # mean steps per probe ray from the best spawns, env's threshold (0: failed)

    def to_json(self) -> dict[str, object]:
        """Plain JSON-ready dict."""
        return asdict(self)

    @property
    def passed(self) -> bool:
        return self.verdict == "pass"


def candidate_grid(lo: torch.Tensor, hi: torch.Tensor, grid: tuple[int, int, int]) -> torch.Tensor:
    """Cell-centred grid points (G, 3) float32 inside the box lo..hi (3,) each, x-major."""
    axes = [
        lo[k] + (torch.arange(grid[k], dtype=torch.float32) + 0.5) * ((hi[k] - lo[k]) / grid[k])
        for k in range(3)
    ]
    x, y, z = torch.meshgrid(*axes, indexing="ij")  # (gx, gy, gz) each
    return torch.stack((x, y, z), dim=-1).reshape(-1, 3)  # (G, 3)


def observation_profile(
    depth: torch.Tensor, hit: torch.Tensor, near_distance: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(starvation (C,), near (C,)) of probe views: depth (C, R) meters, hit (C, R) bool."""
    starvation = 1.0 - hit.to(torch.float32).mean(dim=1)  # (C,)
    near = (hit & (depth < near_distance)).to(torch.float32).mean(dim=1)  # (C,)
    return starvation, near


def candidate_score(starvation: torch.Tensor, near: torch.Tensor, clearance: torch.Tensor) -> torch.Tensor:
    """Score (C,) in [0, 1]: open, structured views far enough from walls score high."""
    return (1.0 - starvation) * (1.0 - near) * (clearance / 2.0).clamp(0.0, 1.0)


def qualify_scene(corpus: SceneCorpus, scene: int, config: QualifyConfig | None = None) -> Qualification:
    """Probe scene `scene` of the corpus and judge it (see the module docstring)."""
    cfg = config or QualifyConfig()
    dev = corpus.device
    info = corpus.infos[scene]
    lo = torch.tensor(info.bounds_min, dtype=torch.float32)  # (3,)
    hi = torch.tensor(info.bounds_max, dtype=torch.float32)  # (3,)
    grid = candidate_grid(lo, hi, cfg.grid)  # (G, 3)
    points = torch.cat([grid, torch.from_numpy(info.spawns).reshape(-1, 3)]).to(dev).contiguous()  # (C, 3)
    c = points.shape[0]
    ids = torch.full((c,), scene, dtype=torch.int64, device=dev)  # (C,)
    inside = sample_distance(corpus, ids, points) > 0.0  # (C,) bool: on the free side of the field
    dirs = ray_pattern(cfg.azimuth_bins, cfg.elevation_bins, SensorConfig(), dev)  # (R, 3)
    depth = torch.empty(c, dirs.shape[0], dtype=torch.float32, device=dev)  # (C, R)
    semantic = torch.empty(c, dirs.shape[0], dtype=torch.uint8, device=dev)  # (C, R) 0 = miss
    trace(
        corpus,
        ids,
        points,
        dirs,
        out_depth=depth,
        out_semantic=semantic,
        max_steps=cfg.trace_max_steps,
        horizon=cfg.horizon,
        hit_epsilon=0.01,
    )
    starvation, near = observation_profile(depth, semantic > 0, cfg.near_distance)  # (C,), (C,)
    # the clearance is the shortest ray, as in the env (a far cube's bound can be far below the truth)
    clearance = torch.where(inside, depth.amin(dim=1), -1.0)  # (C,) meters
    free = clearance >= cfg.min_clearance  # (C,) bool
    viable = free & (starvation < cfg.max_starvation) & (near < cfg.max_near)  # (C,) bool
    score = candidate_score(starvation, near, clearance)  # (C,)
    order = torch.argsort(torch.where(viable, score, -1.0), descending=True, stable=True)  # (C,)
    keep = order[: int(viable.sum())]  # (V,)
    n_free = int(free.sum())
    best = float(starvation[free].min()) if n_free else 1.0
    if n_free == 0:
        verdict, reason = "fail", f"no candidate has clearance >= {cfg.min_clearance} m"
    elif keep.numel() == 0:
        verdict, reason = "fail", "no free candidate has an acceptable view"
    elif best >= cfg.max_starvation:
        verdict, reason = "fail", f"best starvation {best:.2f} >= {cfg.max_starvation}"
    else:
        verdict, reason = "pass", f"{keep.numel()} viable of {c} candidates, best starvation {best:.2f}"
    cost = trace_cost(corpus, scene, points[keep[: cfg.cost_spawns]], cfg) if verdict == "pass" else 0.0
    return Qualification(
        verdict=verdict,
        reason=reason,
        candidates=c,
        free_candidates=n_free,
        viable_spawns=int(keep.numel()),
        best_starvation=round(best, 6),
        spawns=points[keep].cpu().tolist(),
        scores=[round(v, 6) for v in score[keep].cpu().tolist()],
        trace_cost=cost,
    )


def trace_cost(
    corpus: SceneCorpus, scene: int, spawns: torch.Tensor, config: QualifyConfig | None = None
) -> float:
    """Mean sphere-tracing steps per ray of the probe pattern cast from `spawns` (P, 3) in scene `scene`,
    with the env's hit threshold, step cap and horizon (EnvConfig's defaults): how much tracing an actor
    of the scene costs relative to other scenes. Rounded to 1e-4."""
    cfg, env = config or QualifyConfig(), EnvConfig()
    dev = corpus.device
    points = spawns.to(dev, torch.float32).contiguous()  # (P, 3)
    ids = torch.full((points.shape[0],), scene, dtype=torch.int64, device=dev)  # (P,)
    dirs = ray_pattern(cfg.azimuth_bins, cfg.elevation_bins, SensorConfig(), dev)  # (R, 3)
    depth = torch.empty(points.shape[0], dirs.shape[0], dtype=torch.float32, device=dev)  # (P, R)
    steps = torch.empty(points.shape[0], dirs.shape[0], dtype=torch.int32, device=dev)  # (P, R)
    trace(corpus, ids, points, dirs, out_depth=depth, out_steps=steps, max_steps=env.trace_max_steps,
          horizon=env.horizon, hit_epsilon=env.hit_epsilon, hit_slope=env.hit_slope)  # fmt: skip
    return round(float(steps.to(torch.float64).mean()), 4) if points.shape[0] else 0.0


def scene_spawns(corpus: SceneCorpus, scene: int, config: QualifyConfig | None = None) -> torch.Tensor:
    """Viable spawn positions (K, 3) float32 of one scene, best first; raises when it has none."""
    result = qualify_scene(corpus, scene, config)
    if not result.spawns:
        raise ValueError(f"scene {scene} has no viable spawn: {result.reason}")
    return torch.tensor(result.spawns, dtype=torch.float32)  # (K, 3)
