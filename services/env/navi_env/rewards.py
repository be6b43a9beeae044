"""Reward terms: each a small function of per-actor tensors, weighted by `RewardConfig`.

The step reward is the sum of the weighted terms in `TERMS`; `reward_terms` returns each one so the
trainer can log them separately. Observation-derived terms (foraging, structure) use the statistics of
the view the action was chosen on; motion-derived terms use this step's move.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from navi_env.config import EnvConfig, RewardConfig

TERMS: tuple[str, ...] = (
    "collision",
    "progress",
    "proximity",
    "escape",
    "exploration",
    "foraging",
    "structure",
    "existential",
)
"""Names of the reward terms, in the order docs/SIMULATION.md lists them."""

_HASH_PRIMES = (73856093, 19349663, 83492791)


@dataclass(frozen=True)
class RewardInputs:
    """Everything the reward terms read, one value per actor."""

    contact: torch.Tensor  # (N,) bool: contact this step
    speed: torch.Tensor  # (N,) float32 commanded speed after the limiter, m/s
    forward_speed: torch.Tensor  # (N,) float32 speed actually flown along body +X, m/s
    clearance: torch.Tensor  # (N,) float32 clearance after the move, m
    prev_clearance: torch.Tensor  # (N,) float32 clearance before the move, m
    novel: torch.Tensor  # (N,) bool: the drone entered a cell not visited this episode
    void: torch.Tensor  # (N,) float32 fraction of rays that missed (view acted on)
    near: torch.Tensor  # (N,) float32 fraction of rays closer than near_distance
    mid: torch.Tensor  # (N,) float32 fraction of rays in the mid-range band
    mid_prev: torch.Tensor  # (N,) float32 the same fraction one view earlier
    mid_balance: torch.Tensor  # (N,) float32 mid-range fraction on the left minus on the right, [-1, 1]
    yaw_rate: torch.Tensor  # (N,) float32 commanded yaw rate, rad/s (positive: turn left)


def collision_term(
    contact: torch.Tensor, speed: torch.Tensor, max_speed: float, cfg: RewardConfig
) -> torch.Tensor:
    """-(base + speed / max_speed) on contact, 0 otherwise: fast crashes cost more than grazing."""
    return -cfg.collision_weight * contact.to(speed.dtype) * (cfg.collision_base + speed / max_speed)  # (N,)


def proximity_ratio(clearance: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """Clearance / proximity_distance clipped to [0, 1] (N,): 1 in the open, 0 at the surface."""
    return (clearance / cfg.proximity_distance).clamp(0.0, 1.0)


def progress_term(
    forward_speed: torch.Tensor, clearance: torch.Tensor, max_speed: float, cfg: RewardConfig
) -> torch.Tensor:
    """Forward speed / max_speed discounted by the proximity ratio (N,)."""
    return cfg.progress_weight * forward_speed / max_speed * proximity_ratio(clearance, cfg)


def proximity_term(clearance: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """-(1 - proximity ratio)^2 (N,): zero in the open, -weight at the surface."""
    return -cfg.proximity_weight * (1.0 - proximity_ratio(clearance, cfg)).square()


def escape_term(
    prev_clearance: torch.Tensor, clearance: torch.Tensor, max_step: float, cfg: RewardConfig
) -> torch.Tensor:
    """Clearance gained / largest possible step (N,), paid only when the step began near geometry."""
    gain = (clearance - prev_clearance).clamp_min(0.0) / max_step  # (N,)
    near = prev_clearance < cfg.proximity_distance  # (N,) bool
    return cfg.escape_weight * gain * near.to(gain.dtype)


def exploration_term(novel: torch.Tensor, clearance: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """1 for a novel cell entered with clearance >= exploration_min_clearance (N,)."""
    paid = novel & (clearance >= cfg.exploration_min_clearance)  # (N,) bool
    return cfg.exploration_weight * paid.to(clearance.dtype)


def foraging_term(void: torch.Tensor, near: torch.Tensor, cfg: RewardConfig) -> torch.Tensor:
    """-(blind part + near-field part) (N,): a view mostly at the horizon or mostly a wall costs."""
    blind = ((void - cfg.blind_threshold) / (1.0 - cfg.blind_threshold)).clamp(0.0, 1.0)  # (N,)
    return -(cfg.blind_weight * blind + cfg.near_weight * near)


def structure_term(
    mid: torch.Tensor,
    mid_prev: torch.Tensor,
    mid_balance: torch.Tensor,
    yaw_rate: torch.Tensor,
    max_yaw_rate: float,
    cfg: RewardConfig,
) -> torch.Tensor:
    """Stable mid-range structure in view, plus turning toward the side that has more of it (N,)."""
    stable = mid * (1.0 - (mid - mid_prev).abs())  # (N,) in [0, 1]
    turn = mid_balance * yaw_rate / max_yaw_rate  # (N,) in [-1, 1]
    return cfg.structure_weight * stable + cfg.structure_turn_weight * turn


def reward_terms(x: RewardInputs, config: EnvConfig) -> dict[str, torch.Tensor]:
    """Every weighted term (N,) by name, in `TERMS` order; the reward is their sum."""
    cfg = config.reward
    return {
        "collision": collision_term(x.contact, x.speed, config.max_speed, cfg),
        "progress": progress_term(x.forward_speed, x.clearance, config.max_speed, cfg),
        "proximity": proximity_term(x.clearance, cfg),
        "escape": escape_term(x.prev_clearance, x.clearance, config.max_speed * config.dt, cfg),
        "exploration": exploration_term(x.novel, x.clearance, cfg),
        "foraging": foraging_term(x.void, x.near, cfg),
        "structure": structure_term(x.mid, x.mid_prev, x.mid_balance, x.yaw_rate, config.max_yaw_rate, cfg),
        "existential": torch.full_like(x.clearance, cfg.existential_tax),
    }


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


def visit_cells_ref(seen: list[set[int]], index: torch.Tensor) -> torch.Tensor:
    """Slow twin of `visit_cells` on Python sets of bit indices, one set per actor."""
    novel = []
    for n, i in enumerate(index.tolist()):
        novel.append(i not in seen[n])
        seen[n].add(i)
    return torch.tensor(novel, dtype=torch.bool)  # (N,)
