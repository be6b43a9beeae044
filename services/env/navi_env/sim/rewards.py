"""Reward terms: each a small function of per-actor tensors, weighted by `RewardConfig`.

The step reward is the sum of the weighted terms in `TERMS`; `reward_terms` returns each one so the
trainer can log them separately. Every term reads the transition s -> s' of one step:

- state terms (collision, proximity, exploration, foraging, existential) read the move and the state
  after it, and are never positive except exploration, which pays each cell once per episode;
- shaping terms (escape, structure) are potential-based, F = gamma * Phi(s') - Phi(s), with Phi a
  function of the clearance and the view, so the shaping summed over any closed loop of states is
  (gamma - 1) * (sum of Phi along the loop) <= 0: approach-retreat cycles cannot farm it.

docs/SIMULATION.md lists each term with its bound per step (`term_bounds` computes them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from navi_env.config import EnvConfig, RewardConfig

TERMS: tuple[str, ...] = (
    "collision",
    "proximity",
    "escape",
    "exploration",
    "foraging",
    "structure",
    "existential",
)
"""Names of the reward terms, in the order docs/SIMULATION.md lists them."""

SHAPING_TERMS: tuple[str, ...] = ("escape", "structure")
"""The potential-based terms of exploration."""

POINTGOAL_TERMS: tuple[str, ...] = ("collision", "proximity", "escape", "progress", "success", "existential")
"""Names of the reward terms of point-goal episodes: the safety terms, progress toward the goal (potential-
based on the true path length) and the success bonus; none of exploration's seeking terms."""


def task_terms(task: str) -> tuple[str, ...]:
    """The reward terms of a task (EnvConfig.task), in order."""
    return POINTGOAL_TERMS if task == "pointgoal" else TERMS


_HASH_PRIMES = (73856093, 19349663, 83492791)


@dataclass(frozen=True)
class RewardInputs:
    """Everything the reward terms read, one value per actor; `_before` is the state s the action was
    chosen in, the plain name the state s' after the move."""

    contact: torch.Tensor  # (N,) bool: contact this step
    speed: torch.Tensor  # (N,) float32 commanded speed after the limiter, m/s
    novel: torch.Tensor  # (N,) bool: the drone entered a cell not visited this episode
    clearance_before: torch.Tensor  # (N,) float32 view clearance in s, m
    clearance: torch.Tensor  # (N,) float32 view clearance in s', m
    mid_before: torch.Tensor  # (N,) float32 mid-range fraction of the view in s
    mid: torch.Tensor  # (N,) float32 mid-range fraction of the view in s'
    front_mid_before: torch.Tensor  # (N,) float32 mid-range fraction of the front half in s
    front_mid: torch.Tensor  # (N,) float32 mid-range fraction of the front half in s'
    void: torch.Tensor  # (N,) float32 fraction of rays that missed in s'
    near: torch.Tensor  # (N,) float32 fraction of rays closer than near_distance in s'
    progress_before: torch.Tensor | None = None  # (N,) float32 point-goal: max(d0 - d, 0) in s, m
    progress: torch.Tensor | None = None  # (N,) float32 point-goal: max(d0 - d, 0) in s', m
    success: torch.Tensor | None = None  # (N,) bool point-goal: s' is at the goal, slow enough


def collision_term(
    contact: torch.Tensor, speed: torch.Tensor, max_speed: float, cfg: RewardConfig, task: str = "explore"
) -> torch.Tensor:
    """-(base + speed / max_speed) on contact, 0 otherwise: fast crashes cost more than grazing; weighted
    by the task's collision price (RewardConfig.collision_price)."""
    weight = cfg.collision_price(task)
    return -weight * contact.to(speed.dtype) * (cfg.collision_base + speed / max_speed)  # (N,)


def proximity_ratio(clearance: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """Clearance / proximity_distance clipped to [0, 1] (N,): 1 in the open, 0 at the surface."""
    return (clearance / cfg.proximity_distance).clamp(0.0, 1.0)


def proximity_term(clearance: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """-(1 - proximity ratio)^2 of the state after the move (N,): zero in the open, -weight at the surface."""
    return -cfg.proximity_weight * (1.0 - proximity_ratio(clearance, cfg)).square()


def escape_potential(clearance: torch.Tensor, max_step: float, cfg: RewardConfig) -> torch.Tensor:
    """Phi_escape (N,) = weight * min(clearance, proximity_distance) / max_step, in [0, weight * d / step]."""
    return cfg.escape_weight * clearance.clamp(0.0, cfg.proximity_distance) / max_step


def structure_potential(mid: torch.Tensor, front_mid: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """Phi_structure (N,) = w * mid-range fraction + w_front * front mid-range fraction, in [0, w + w_front]."""
    return cfg.structure_weight * mid + cfg.structure_front_weight * front_mid


def shaping(phi_before: torch.Tensor, phi: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """Potential-based shaping (N,): gamma * Phi(s') - Phi(s)."""
    return cfg.shaping_gamma * phi - phi_before


def exploration_term(novel: torch.Tensor, clearance: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """1 for a novel cell entered with clearance >= exploration_min_clearance (N,)."""
    paid = novel & (clearance >= cfg.exploration_min_clearance)  # (N,) bool
    return cfg.exploration_weight * paid.to(clearance.dtype)


def foraging_term(void: torch.Tensor, near: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """-(blind part + near-field part) (N,): a view mostly at the horizon or mostly a wall costs."""
    blind = ((void - cfg.blind_threshold) / (1.0 - cfg.blind_threshold)).clamp(0.0, 1.0)  # (N,)
    return -(cfg.blind_weight * blind + cfg.near_weight * near)


def goal_potential(progress: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """Phi_goal (N,) = progress_weight * max(d0 - d, 0) from that progress (N,) meters: highest at the goal,
    0 at the start distance and beyond."""
    return cfg.progress_weight * progress


def reward_terms(x: RewardInputs, config: EnvConfig) -> dict[str, torch.Tensor]:
    """Every weighted term (N,) by name, in `task_terms(config.task)` order; the reward is their sum."""
    cfg = config.reward
    step = config.max_speed * config.dt
    escape = shaping(
        escape_potential(x.clearance_before, step, cfg), escape_potential(x.clearance, step, cfg), cfg
    )
    if config.task == "pointgoal":
        assert x.progress_before is not None and x.progress is not None and x.success is not None
        return {
            "collision": collision_term(x.contact, x.speed, config.max_speed, cfg, config.task),
            "proximity": proximity_term(x.clearance, cfg),
            "escape": escape,
            "progress": shaping(goal_potential(x.progress_before, cfg), goal_potential(x.progress, cfg), cfg),
            "success": cfg.success_weight * x.success.to(x.clearance.dtype),
            "existential": torch.full_like(x.clearance, cfg.existential_tax),
        }
    structure = shaping(
        structure_potential(x.mid_before, x.front_mid_before, cfg),
        structure_potential(x.mid, x.front_mid, cfg),
        cfg,
    )
    return {
        "collision": collision_term(x.contact, x.speed, config.max_speed, cfg),
        "proximity": proximity_term(x.clearance, cfg),
        "escape": escape,
        "exploration": exploration_term(x.novel, x.clearance, cfg),
        "foraging": foraging_term(x.void, x.near, cfg),
        "structure": structure,
        "existential": torch.full_like(x.clearance, cfg.existential_tax),
    }


def term_bounds(config: EnvConfig, clearance_change: float) -> dict[str, tuple[float, float]]:
    """The documented (low, high) bound of every term per step, given a bound on how much the clearance
    can change in one step, `clearance_change` meters (the distance flown plus the tracer's error).

    Escape: |gamma * Phi' - Phi| <= w * min(change, d) / step + (1 - gamma) * Phi_max on either side.
    Structure: Phi in [0, Phi_max], so gamma * Phi' - Phi lies in [-Phi_max, gamma * Phi_max].
    Progress (point-goal): the path length read between voxel centres changes by at most the clearance
    change's bound plus one voxel diagonal, and Phi_goal lies in [0, w * goal.far] (the env clamps the
    progress there), so the term lies within +-w * that change, minus (1 - gamma) * w * goal.far below.
    Success: [0, success_weight].
    """
    cfg = config.reward
    step = config.max_speed * config.dt
    g = cfg.shaping_gamma
    escape_max = cfg.escape_weight * cfg.proximity_distance / step  # Phi_escape's largest value
    escape_swing = cfg.escape_weight * min(clearance_change, cfg.proximity_distance) / step
    structure_max = cfg.structure_weight + cfg.structure_front_weight
    goal_swing = cfg.progress_weight * (clearance_change + math.sqrt(3.0) * config.goal.cell)
    goal = {
        "progress": (-goal_swing - (1.0 - g) * cfg.progress_weight * config.goal.far, goal_swing),
        "success": (0.0, cfg.success_weight),
    }
    bounds = {
        "collision": (-cfg.collision_price(config.task) * (cfg.collision_base + 1.0), 0.0),
        "proximity": (-cfg.proximity_weight, 0.0),
        "escape": (-escape_swing - (1.0 - g) * escape_max, escape_swing),
        "exploration": (0.0, cfg.exploration_weight),
        "foraging": (-(cfg.blind_weight + cfg.near_weight), 0.0),
        "structure": (-structure_max, g * structure_max),
        "existential": (cfg.existential_tax, cfg.existential_tax),
    } | goal
    return {name: bounds[name] for name in task_terms(config.task)}


def cell_index(position: torch.Tensor, cell: float, bits: int) -> torch.Tensor:
    """Hash the exploration cell of each position (N, 3) meters into a bit index (N,) int64 in [0, 2^bits)."""
    c = torch.floor(position / cell).to(torch.int64)  # (N, 3)
    h = (c[:, 0] * _HASH_PRIMES[0]) ^ (c[:, 1] * _HASH_PRIMES[1]) ^ (c[:, 2] * _HASH_PRIMES[2])  # (N,)
    return h & ((1 << bits) - 1)


def visit_cells(visited: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Mark bit `index` (N,) int64 in each actor's bitmap `visited` (N, M/8) uint8, in place.

    Returns novel (N,) bool: the bit was clear before. Hash collisions can only hide novelty.
    """
    byte = (index >> 3)[:, None]  # (N, 1) int64
    mask = torch.bitwise_left_shift(torch.ones_like(index), index & 7).to(torch.uint8)[:, None]  # (N, 1)
    word = visited.gather(1, byte)  # (N, 1) uint8
    novel = (word & mask) == 0  # (N, 1) bool
    visited.scatter_(1, byte, word | mask)
    return novel[:, 0]


def visit(visited: torch.Tensor, position: torch.Tensor, cell: float, bits: int) -> torch.Tensor:
    """Mark the exploration cells of positions (N, 3) in `visited` (N, M/8) uint8 (cell_index, then
    visit_cells); returns novel (N,) bool."""
    return visit_cells(visited, cell_index(position, cell, bits))


def visit_cells_ref(seen: list[set[int]], index: torch.Tensor) -> torch.Tensor:
    """Slow twin of `visit_cells` on Python sets of bit indices, one set per actor."""
    novel = []
    for n, i in enumerate(index.tolist()):
        novel.append(i not in seen[n])
        seen[n].add(i)
    return torch.tensor(novel, dtype=torch.bool)  # (N,)
