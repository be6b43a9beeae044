"""Point-goal episodes of a scene: goals that can be reached from its spawns, and true path lengths to them.

A GoalTable holds G goal voxels of the scene's free space (navi_env.space.freespace), each with its
geodesic field (the path length in meters from every voxel to the goal through free voxels and the
space's passable edges: steps between neighbouring voxel centres whose straight segment the tracer found
clear of every surface, so a path never goes through a wall, however thin against the cell), and which
spawns pair with which goals: same connected part, and a path length within [near, far] (default 5 to
30 m). An episode starts at a spawn and draws one of its goals; `distance` reads the path length from
any world point (between voxel centres: the best of the 8 surrounding centres plus the straight hop to
it), which is what a potential-based reward reads every step.

Goals are drawn once per scene with a seeded generator: the candidates are free voxels with at least
`goal_clearance` meters of clearance in the parts that hold a spawn; a candidate that no spawn pairs
with is dropped. Built on the scene's device; `goal_table_ref` is the plain-Python twin of the pairing
(Dijkstra per goal) for small grids.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch

from navi_env.space.freespace import FreeSpace, components, geodesic_many, geodesic_ref

CORNERS = torch.tensor(list(itertools.product((0, 1), repeat=3)))
"""(8, 3) offsets from the lower corner voxel to the 8 voxel centres around a point."""


@dataclass(frozen=True)
class GoalTable:
    """One scene's goals (see the module docstring)."""

    space: FreeSpace
    goals: torch.Tensor  # (G, 3) int64 goal voxels
    fields: torch.Tensor  # (G, X, Y, Z) float32 path length to each goal, meters (inf: no path)
    pairs: torch.Tensor  # (K, G) bool spawn k may start an episode toward goal g

    @property
    def positions(self) -> torch.Tensor:
        """(G, 3) float32 world positions of the goals (their voxel centres)."""
        return self.space.centre_of(self.goals)

    def nbytes(self) -> int:
        """Device bytes of the table (fields, goals, pairs)."""
        return sum(t.numel() * t.element_size() for t in (self.fields, self.goals, self.pairs))

    def distance(self, goal: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Path length (N,) float32 meters from world points (N, 3) to goals `goal` (N,) int64: over the 8
        voxel centres around each point, the least field value plus the straight distance to that
        centre (inf when none of them has a path)."""
        space = self.space
        origin = torch.tensor(space.origin, dtype=torch.float32, device=points.device)  # (3,)
        shape = torch.tensor(space.free.shape, device=points.device)  # (3,) int64
        low = torch.floor((points - origin) / space.cell - 0.5).long()  # (N, 3) the lower corner voxel
        corners = (low[:, None, :] + CORNERS.to(points.device)[None]).clamp(min=0)  # (N, 8, 3)
        corners = torch.minimum(corners, shape - 1)
        value = self.fields[goal[:, None], corners[..., 0], corners[..., 1], corners[..., 2]]  # (N, 8)
        centre = space.centre_of(corners.reshape(-1, 3)).reshape(-1, 8, 3)  # (N, 8, 3)
        hop = (centre - points[:, None, :]).norm(dim=-1)  # (N, 8)
        return (value + hop).amin(dim=1)


def goal_table(
    space: FreeSpace,
    spawns: torch.Tensor,
    count: int = 16,
    near: float = 5.0,
    far: float = 30.0,
    goal_clearance: float = 0.5,
    seed: int = 0,
) -> GoalTable:
    """Up to `count` goals of the scene whose free space is `space`, for spawns (K, 3) world meters (see
    the module docstring); raises when no spawn can reach any candidate within [near, far]."""
    if not 0.0 <= near < far:
        raise ValueError(f"need 0 <= near < far, got {near}, {far}")
    labels = components(space.free, space.edges)  # (X, Y, Z)
    start = space.voxel(spawns.to(space.free.device))  # (K, 3)
    spawn_parts = labels[start[:, 0], start[:, 1], start[:, 2]]  # (K,)
    candidates = torch.isin(labels, spawn_parts[spawn_parts >= 0]) & (space.clearance >= goal_clearance)
    pool = candidates.nonzero()  # (C, 3)
    g = torch.Generator().manual_seed(seed)
    order = torch.randperm(pool.shape[0], generator=g)[: 4 * count].to(pool.device)  # a few spares
    goals: list[torch.Tensor] = []  # (3,) int64 each
    fields: list[torch.Tensor] = []  # (X, Y, Z) float32 each
    pairs: list[torch.Tensor] = []  # (K,) bool each
    candidates = pool[order]  # (C', 3)
    for first in range(0, candidates.shape[0], count):  # a batch of fields at a time
        if len(goals) == count:
            break
        batch = candidates[first : first + count]  # (B, 3)
        field = geodesic_many(space.free, batch, space.cell, space.edges)  # (B, X, Y, Z)
        reach = field[:, start[:, 0], start[:, 1], start[:, 2]]  # (B, K) path length from each spawn's voxel
        paired = (reach >= near) & (reach <= far)  # (B, K) bool
        for b in paired.any(dim=1).nonzero()[:, 0].tolist():
            if len(goals) < count:
                goals.append(batch[b])
                fields.append(field[b])
                pairs.append(paired[b])
    if not goals:
        raise ValueError(f"no goal within {near}-{far} m of any spawn (of {pool.shape[0]} candidates)")
    return GoalTable(space, torch.stack(goals), torch.stack(fields), torch.stack(pairs, dim=1))


def goal_table_ref(table: GoalTable, spawns: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """The pairs (K, G) bool of `table`'s goals recomputed by Dijkstra from each goal (small grids)."""
    start = table.space.voxel(spawns.cpu()).tolist()  # K x [i, j, k]
    columns = []
    for goal in table.goals.cpu():
        field = geodesic_ref(table.space.free, goal[None], table.space.cell, table.space.edges)  # (X, Y, Z)
        columns.append([near <= float(field[tuple(s)]) <= far for s in start])
    return torch.tensor(columns, dtype=torch.bool).T  # (K, G)
