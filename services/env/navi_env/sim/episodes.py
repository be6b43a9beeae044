"""Episode lifecycle as tensor ops: truncation, starvation, scene rotation and spawn selection.

No host synchronisation: every choice is made for all actors at once with masks, and random choices
come from navi_env.sim.rng (counter-based, identical on CPU and CUDA).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from navi_env.config import EnvConfig
from navi_env.sim import rng


@dataclass(frozen=True)
class SpawnTable:
    """Quality-gated spawn positions of every scene, padded into one device table."""

    position: torch.Tensor  # (S_scenes, K, 3) float32 world meters (rows past count repeat row 0)
    clearance: torch.Tensor  # (S_scenes, K) float32 clearance at each position, meters
    count: torch.Tensor  # (S_scenes,) int64 valid rows per scene, >= 1

    @property
    def scenes(self) -> int:
        return int(self.count.shape[0])


def spawn_table(
    positions: Sequence[torch.Tensor], clearances: Sequence[torch.Tensor], device: torch.device | str
) -> SpawnTable:
    """Pad per-scene spawn lists (K_s, 3) and clearances (K_s,) into a SpawnTable on `device`."""
    if not positions or len(positions) != len(clearances):
        raise ValueError("need one spawn list and one clearance list per scene")
    for s, (p, c) in enumerate(zip(positions, clearances, strict=True)):
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0 or c.shape != (p.shape[0],):
            raise ValueError(f"scene {s}: spawns must be (K, 3) with K >= 1 and clearances (K,)")
    k = max(p.shape[0] for p in positions)
    pos = torch.stack([torch.cat([p, p[:1].expand(k - p.shape[0], 3)]) for p in positions])  # (S, K, 3)
    clr = torch.stack([torch.cat([c, c[:1].expand(k - c.shape[0])]) for c in clearances])  # (S, K)
    count = torch.tensor([p.shape[0] for p in positions], dtype=torch.int64)  # (S,)
    return SpawnTable(
        position=pos.to(device=device, dtype=torch.float32).contiguous(),
        clearance=clr.to(device=device, dtype=torch.float32).contiguous(),
        count=count.to(device),
    )


def pick_index(u: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """Index (N,) int64 in [0, count) from uniforms u (N,) in [0, 1) and counts (N,) int64 >= 1."""
    return torch.minimum((u * count.to(u.dtype)).to(torch.int64), count - 1)


def draw_spawns(
    table: SpawnTable,
    scene: torch.Tensor,
    seed: torch.Tensor,
    tick: torch.Tensor,
    actor: torch.Tensor,
    squad: int = 1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Spawn position (N, 3), its clearance (N,), a heading (N,) in [-pi, pi) and the spawn's row (N,)
    int64 of the table per actor. With squads
    of `squad` consecutive actors (one scene each), member m takes the squad's draw shifted by
    m * (count // squad) rows, so members start at different points when the scene has enough."""
    count = table.count[scene]  # (N,)
    if squad > 1:
        leader = actor - actor % squad  # (N,)
        first = pick_index(rng.uniform(seed, rng.STREAM_SPAWN, tick, leader), count)  # (N,)
        k = (first + (actor % squad) * torch.clamp_min(count // squad, 1)) % count  # (N,)
    else:
        k = pick_index(rng.uniform(seed, rng.STREAM_SPAWN, tick, actor), count)  # (N,)
    yaw = (rng.uniform(seed, rng.STREAM_YAW, tick, actor) * 2.0 - 1.0) * math.pi  # (N,)
    return table.position[scene, k], table.clearance[scene, k], yaw, k


def next_scene(
    scene: torch.Tensor, n_scenes: int, seed: torch.Tensor, tick: torch.Tensor, actor: torch.Tensor
) -> torch.Tensor:
    """A different scene (N,) int64 for every actor, uniform over the others (same scene if only one)."""
    if n_scenes == 1:
        return scene
    hop = 1 + pick_index(
        rng.uniform(seed, rng.STREAM_SCENE, tick, actor), torch.full_like(scene, n_scenes - 1)
    )
    return (scene + hop) % n_scenes


def truncation(
    steps: torch.Tensor, void: torch.Tensor, config: EnvConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """(time_limit (N,) bool, starved (N,) bool) after an actor's `steps` (N,) steps of this episode.

    `void` (N,) is the miss fraction of the view the last action was chosen on. Starvation needs
    steps > void_grace_steps, so the first void_grace_steps steps after a reset never starve.
    """
    time_limit = steps >= config.max_steps_per_episode  # (N,) bool
    starved = (void >= config.starvation_threshold) & (steps > config.void_grace_steps)  # (N,) bool
    return time_limit, starved & ~time_limit


def rotation(
    episodes_on_scene: torch.Tensor, ended: torch.Tensor, config: EnvConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Count ended episodes on the current scene (N,) int64; rotate (N,) bool where the count is full.

    Returns the updated count (0 for actors that rotate) and the rotate mask.
    """
    count = episodes_on_scene + ended.to(episodes_on_scene.dtype)  # (N,)
    rotate = count >= config.episodes_per_scene  # (N,) bool
    return torch.where(rotate, torch.zeros_like(count), count), rotate
