"""Point-goal episodes as tensor ops: every scene's goals in one device table, the goal draw at a spawn,
the true path length to the goal from any point, and the goal mark in the observation.

The GoalBank is built once, when a point-goal env is created (`goal_bank`): per scene, the free space at
the drone's radius, its goals and their path-length fields (navi_env.space.goal_tables.GoalTable), and which
spawn pairs with which goal. Spawns that no goal pairs with are dropped from that env's spawn table.

The goal reaches the policy through the observation only (docs/TASKS.md): `paint_goal` writes the goal
mark into channel 1 (semantic) at the bins within GoalConfig.mark_degrees of the straight-line
direction to the goal, whatever lies between, with a value that gives the straight-line distance in
one of MARK_BANDS bands. Scene hits keep channel 1 in [0.5, 1] and misses 0; the mark is negative.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from navi_env.config import EnvConfig, GoalConfig
from navi_env.sim import rng
from navi_env.sim.episodes import pick_index
from navi_env.sim.observation import MARK_BANDS
from navi_env.space.freespace import free_space, lattice_cell
from navi_env.space.goal_tables import CORNERS, GoalTable, goal_table
from navi_env.tracer.scene import SceneCorpus

MARK_EDGES: tuple[float, ...] = (
    0.25,
    0.5,
    0.75,
    1.0,
    1.5,
    2.0,
    3.0,
    4.0,
    6.0,
    8.0,
    12.0,
    16.0,
    24.0,
    32.0,
    48.0,
)
"""Upper edges (m) of the distance bands of the goal mark; the last band is everything beyond 48 m."""
assert len(MARK_EDGES) + 1 == MARK_BANDS  # band b reads -(b + 1) / B in channel 1, code FIRST_MARK_CODE + b


@dataclass(frozen=True)
class GoalBank:
    """Every scene's goals and path-length fields on the env's device; goal j = scene * G + g."""

    fields: torch.Tensor  # (V,) float32 every goal's path-length field, flattened one after another
    offset: torch.Tensor  # (S * G,) int64 where goal j's field starts in `fields`
    shape: torch.Tensor  # (S, 3) int64 lattice voxels per axis, per scene
    origin: torch.Tensor  # (S, 3) float32 world position of each lattice's lower corner
    cell: torch.Tensor  # (S,) float32 voxel edge per scene, meters
    position: torch.Tensor  # (S * G, 3) float32 goal world positions (voxel centres)
    pairs: torch.Tensor  # (S, K, G) bool spawn row k of scene s may start toward its goal g
    corners: torch.Tensor  # (8, 3) int64 CORNERS on the device (a step never copies from the host)
    edges: torch.Tensor  # (B - 1,) float32 MARK_EDGES on the device
    per_scene: int  # G (scenes with fewer goals never pair with the padded ones)

    def nbytes(self) -> int:
        """Device bytes of the bank."""
        return sum(
            t.numel() * t.element_size()
            for t in (self.fields, self.offset, self.shape, self.origin, self.cell, self.position, self.pairs)
        )


def build_tables(
    corpus: SceneCorpus, spawns: Sequence[torch.Tensor], cfg: GoalConfig, radius: float
) -> list[GoalTable]:
    """One GoalTable per scene of the corpus for its spawns (K_s, 3); ValueError names a scene where no
    spawn has a goal within [near, far]."""
    return [scene_table(corpus, s, points, cfg, radius) for s, points in enumerate(spawns)]


def scene_table(
    corpus: SceneCorpus, scene: int, spawns: torch.Tensor, cfg: GoalConfig, radius: float
) -> GoalTable:
    """The GoalTable of one scene of the corpus for its spawns (K, 3); ValueError, naming the scene, where
    no spawn has a goal within [near, far]."""
    cell = lattice_cell(corpus, scene, cfg.cell, cfg.max_voxels)
    space = free_space(corpus, scene, cell, radius)
    try:
        return goal_table(
            space, spawns, cfg.per_scene, cfg.near, cfg.far, cfg.clearance, seed=cfg.seed + scene
        )
    except ValueError as err:
        raise ValueError(f"scene {corpus.infos[scene].name!r}: {err}") from None


def goal_bank(
    tables: Sequence[GoalTable], spawns: Sequence[torch.Tensor], device: torch.device
) -> tuple[GoalBank, list[torch.Tensor]]:
    """The bank of per-scene tables, and each scene's spawns (K'_s, 3) that pair with at least one goal
    (the rows of the bank's pair table, in order)."""
    g = max(t.goals.shape[0] for t in tables)
    kept = [points[t.pairs.any(dim=1).cpu()] for t, points in zip(tables, spawns, strict=True)]
    k = max(p.shape[0] for p in kept)
    pairs = torch.zeros(len(tables), k, g, dtype=torch.bool)  # (S, K, G)
    fields, offsets, positions = [], [], []
    start = 0
    for s, t in enumerate(tables):
        rows = t.pairs[t.pairs.any(dim=1)].cpu()  # (K'_s, G_s)
        pairs[s, : rows.shape[0], : rows.shape[1]] = rows
        pairs[s, rows.shape[0] :, : rows.shape[1]] = rows[:1]  # padded spawn rows repeat row 0
        size = math.prod(t.space.free.shape)
        for j in range(g):
            offsets.append(start + min(j, t.goals.shape[0] - 1) * size)
        fields.append(t.fields.reshape(-1).to(device))
        pos = t.positions.to(device)  # (G_s, 3)
        positions.append(torch.cat([pos, pos[:1].expand(g - pos.shape[0], 3)]))
        start += t.fields.numel()
    bank = GoalBank(
        fields=torch.cat(fields),
        offset=torch.tensor(offsets, dtype=torch.int64, device=device),
        shape=torch.tensor([t.space.free.shape for t in tables], dtype=torch.int64, device=device),
        origin=torch.tensor([t.space.origin for t in tables], dtype=torch.float32, device=device),
        cell=torch.tensor([t.space.cell for t in tables], dtype=torch.float32, device=device),
        position=torch.cat(positions).contiguous(),
        pairs=pairs.to(device),
        corners=CORNERS.to(device),
        edges=torch.tensor(MARK_EDGES, dtype=torch.float32, device=device),
        per_scene=g,
    )
    return bank, kept


def draw_goal(
    bank: GoalBank,
    scene: torch.Tensor,
    row: torch.Tensor,
    seed: torch.Tensor,
    tick: torch.Tensor,
    actor: torch.Tensor,
) -> torch.Tensor:
    """Goal j (N,) int64 per actor, uniform over the goals that spawn row `row` (N,) of `scene` (N,) pairs
    with (every kept spawn has one)."""
    paired = bank.pairs[scene, row]  # (N, G) bool
    pick = pick_index(rng.uniform(seed, rng.STREAM_GOAL, tick, actor), paired.sum(dim=1))  # (N,)
    g = (paired.cumsum(dim=1) <= pick[:, None]).sum(dim=1)  # (N,) the (pick + 1)-th paired goal
    return scene * bank.per_scene + g


def goal_distance(
    bank: GoalBank, goal: torch.Tensor, scene: torch.Tensor, points: torch.Tensor
) -> torch.Tensor:
    """True path length (N,) float32 meters from world points (N, 3) to goals `goal` (N,) of scenes
    `scene` (N,): over the 8 voxel centres around each point, the least field value plus the straight
    hop to that centre (GoalTable.distance, for every scene at once); inf when none of them is free."""
    origin, cell, shape = bank.origin[scene], bank.cell[scene, None], bank.shape[scene]  # (N,3), (N,1), (N,3)
    low = torch.floor((points - origin) / cell - 0.5).long()  # (N, 3) the lower corner voxel
    corners = torch.minimum((low[:, None, :] + bank.corners[None]).clamp(min=0), shape[:, None] - 1)
    flat = (corners[..., 0] * shape[:, 1, None] + corners[..., 1]) * shape[:, 2, None] + corners[
        ..., 2
    ]  # (N, 8)
    value = bank.fields[bank.offset[goal][:, None] + flat]  # (N, 8)
    centre = (
        origin.double()[:, None] + (corners.double() + 0.5) * cell.double()[:, None]
    ).float()  # (N, 8, 3)
    hop = (centre - points[:, None, :]).norm(dim=-1)  # (N, 8)
    return (value + hop).amin(dim=1)


def mark_band(distance: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Band (N,) int64 in [0, B) of straight-line distances (N,) meters, for MARK_EDGES as a tensor `edges`
    (B - 1,) (GoalBank.edges): band b holds distances in (edges[b - 1], edges[b]]."""
    return torch.bucketize(distance, edges)


def mark_value(band: torch.Tensor) -> torch.Tensor:
    """Channel 1 (N,) float32 of the goal mark in band `band` (N,): -(band + 1) / B, in [-1, -1/16]."""
    return -(band + 1).to(torch.float32) / MARK_BANDS


def mark_window(config: EnvConfig) -> tuple[int, int]:
    """Half widths (azimuth, elevation) in bins of the goal mark, at least 1 azimuth bin and 0 elevation."""
    az_step = 360.0 / config.azimuth_bins
    el_step = (config.sensor.elevation_max_deg - config.sensor.elevation_min_deg) / config.elevation_bins
    deg = config.goal.mark_degrees
    return max(1, round(deg / az_step)), round(deg / el_step)


def paint_goal(
    obs: torch.Tensor, offset: torch.Tensor, yaw: torch.Tensor, config: EnvConfig, edges: torch.Tensor
) -> None:
    """Write the goal mark into channel 1 of obs (N, 3, Az, El) in place, for goals at world offsets
    (N, 3) (goal minus drone position) seen from headings yaw (N,); `edges` is GoalBank.edges. The mark
    covers the bins within the mark window around the bin of the goal's direction in the body frame
    (azimuth wraps round; elevation stops at the pattern's edges, a goal outside the pattern is marked
    at the nearest edge row)."""
    n, _, az, el = obs.shape
    da, de = mark_window(config)
    c, s = torch.cos(yaw), torch.sin(yaw)  # (N,)
    x = c * offset[:, 0] + s * offset[:, 1]  # (N,) body frame: world offset turned by -yaw
    y = -s * offset[:, 0] + c * offset[:, 1]  # (N,)
    horizontal = torch.sqrt(x * x + y * y)  # (N,)
    azimuth = torch.remainder(torch.atan2(y, x), 2.0 * math.pi)  # (N,) radians in [0, 2 pi)
    elevation = torch.rad2deg(torch.atan2(offset[:, 2], horizontal))  # (N,) degrees
    lo, hi = config.sensor.elevation_min_deg, config.sensor.elevation_max_deg
    a0 = torch.round(azimuth * (az / (2.0 * math.pi))).long() % az  # (N,) nearest azimuth bin
    e0 = torch.floor((elevation - lo) * (el / (hi - lo))).long().clamp(0, el - 1)  # (N,) its elevation bin
    da_range = torch.arange(-da, da + 1, device=obs.device)  # (2da+1,)
    de_range = torch.arange(-de, de + 1, device=obs.device)  # (2de+1,)
    a = (a0[:, None, None] + da_range[None, :, None]) % az  # (N, 2da+1, 1)
    e = (e0[:, None, None] + de_range[None, None, :]).clamp(0, el - 1)  # (N, 1, 2de+1)
    flat = (a * el + e).reshape(n, -1)  # (N, W) ray indices of the window
    value = mark_value(mark_band(offset.norm(dim=1), edges))  # (N,)
    obs[:, 1].view(n, az * el).scatter_(1, flat, value[:, None].expand(-1, flat.shape[1]))


def paint_goal_ref(obs: torch.Tensor, offset: torch.Tensor, yaw: torch.Tensor, config: EnvConfig) -> None:
    """paint_goal by angles, one actor and one bin at a time (small batches): a bin is marked when its
    azimuth and elevation bin lie within the window of the goal's bins."""
    n, _, az, el = obs.shape
    da, de = mark_window(config)
    lo, hi = config.sensor.elevation_min_deg, config.sensor.elevation_max_deg
    for i in range(n):
        dx, dy, dz = (float(v) for v in offset[i])
        heading = math.atan2(dy, dx) - float(yaw[i])
        bearing = math.degrees(heading) % 360.0
        a0 = round(bearing / (360.0 / az)) % az
        elevation = math.degrees(math.atan2(dz, math.hypot(dx, dy)))
        e0 = min(max(math.floor((elevation - lo) / ((hi - lo) / el)), 0), el - 1)
        distance = math.sqrt(dx * dx + dy * dy + dz * dz)
        band = sum(distance > edge for edge in MARK_EDGES)
        for a in range(az):
            ring = min((a - a0) % az, (a0 - a) % az)
            for e in range(el):
                if ring <= da and abs(e - e0) <= de:
                    obs[i, 1, a, e] = -(band + 1) / MARK_BANDS
