"""Every reward term on hand-built cases: its sign and its scale."""

from __future__ import annotations

import math

import torch

from navi_env.config import EnvConfig, RewardConfig
from navi_env.rewards import (
    TERMS,
    RewardInputs,
    cell_index,
    collision_term,
    escape_term,
    exploration_term,
    foraging_term,
    progress_term,
    proximity_term,
    reward_terms,
    structure_term,
    visit_cells,
    visit_cells_ref,
)

CFG = EnvConfig()
R = CFG.reward


def t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=torch.float32)


def test_collision_penalty_scales_with_speed() -> None:
    out = collision_term(torch.tensor([False, True, True]), t(5.0, 0.0, 5.0), 5.0, R)
    assert float(out[0]) == 0.0
    assert math.isclose(float(out[1]), -R.collision_weight * R.collision_base, rel_tol=1e-6)  # grazing
    assert math.isclose(
        float(out[2]), -R.collision_weight * (R.collision_base + 1.0), rel_tol=1e-6
    )  # full speed
    assert float(out[2]) < float(out[1]) < 0.0


def test_progress_is_off_by_default_and_discounted_near_walls() -> None:
    assert float(progress_term(t(5.0), t(10.0), 5.0, R).abs().sum()) == 0.0  # weight 0.0 by default
    cfg = RewardConfig(progress_weight=1.0)
    out = progress_term(t(5.0, 5.0, 5.0, -5.0), t(10.0, 1.0, 0.0, 10.0), 5.0, cfg)
    assert torch.allclose(out, t(1.0, 1.0 / cfg.proximity_distance, 0.0, -1.0))


def test_proximity_shaping_grows_toward_the_surface() -> None:
    out = proximity_term(t(5.0, 2.0, 1.0, 0.0), R)
    assert float(out[0]) == 0.0 and float(out[1]) == 0.0
    assert math.isclose(float(out[2]), -R.proximity_weight * 0.25, rel_tol=1e-6)
    assert math.isclose(float(out[3]), -R.proximity_weight, rel_tol=1e-6)


def test_escape_pays_for_gained_clearance_only_near_geometry() -> None:
    step = CFG.max_speed * CFG.dt
    out = escape_term(t(0.5, 0.5, 5.0), t(1.0, 0.2, 6.0), step, R)
    assert math.isclose(float(out[0]), R.escape_weight * 0.5 / step, rel_tol=1e-6)  # gained 0.5 m near a wall
    assert float(out[1]) == 0.0  # lost clearance: no escape reward (proximity handles the cost)
    assert float(out[2]) == 0.0  # already in the open


def test_exploration_pays_novel_cells_only_with_clearance() -> None:
    out = exploration_term(torch.tensor([True, True, False]), t(2.0, 0.5, 2.0), R)
    assert torch.allclose(out, t(R.exploration_weight, 0.0, 0.0))  # wall hugging earns nothing


def test_foraging_penalises_blind_and_wall_hugging_views() -> None:
    out = foraging_term(t(0.2, 1.0, 0.2), t(0.0, 0.0, 1.0), R)
    assert float(out[0]) == 0.0  # a structured view costs nothing
    assert math.isclose(float(out[1]), -R.blind_weight, rel_tol=1e-6)  # all horizon: blind
    assert math.isclose(float(out[2]), -R.near_weight, rel_tol=1e-6)  # all near field: hugging


def test_structure_rewards_stable_mid_range_and_turning_toward_it() -> None:
    mid = t(0.8, 0.8, 0.8, 0.8)
    prev = t(0.8, 0.3, 0.8, 0.8)
    balance = t(0.0, 0.0, 0.5, 0.5)
    yaw_rate = t(0.0, 0.0, CFG.max_yaw_rate, -CFG.max_yaw_rate)
    out = structure_term(mid, prev, balance, yaw_rate, CFG.max_yaw_rate, R)
    assert math.isclose(float(out[0]), R.structure_weight * 0.8, rel_tol=1e-6)
    assert float(out[1]) < float(out[0])  # unstable view pays less
    assert math.isclose(
        float(out[2] - out[0]), R.structure_turn_weight * 0.5, rel_tol=1e-5
    )  # turning left, toward it
    assert math.isclose(float(out[3] - out[0]), -R.structure_turn_weight * 0.5, rel_tol=1e-5)  # turning away


def test_existential_tax_and_terms_sum() -> None:
    z = torch.zeros(2)
    x = RewardInputs(
        contact=torch.tensor([False, True]),
        speed=t(0.0, 3.0),
        forward_speed=t(0.0, 2.0),
        clearance=t(10.0, 0.2),
        prev_clearance=t(10.0, 0.1),
        novel=torch.tensor([False, True]),
        void=t(0.0, 0.9),
        near=t(0.0, 0.4),
        mid=z,
        mid_prev=z,
        mid_balance=z,
        yaw_rate=z,
    )
    terms = reward_terms(x, CFG)
    assert tuple(terms) == TERMS
    assert torch.allclose(terms["existential"], t(-0.02, -0.02))
    idle = sum(float(v[0]) for v in terms.values())
    assert math.isclose(idle, -0.02, rel_tol=1e-6)  # an idle drone in the open pays only the tax
    assert sum(float(v[1]) for v in terms.values()) < -1.0  # a crash into a wall is strongly negative


def test_visited_cells_bitmap_matches_sets() -> None:
    g = torch.Generator().manual_seed(0)
    n, bits = 6, 8
    visited = torch.zeros(n, (1 << bits) // 8, dtype=torch.uint8)
    seen: list[set[int]] = [set() for _ in range(n)]
    for _ in range(60):
        pos = torch.randint(-4, 4, (n, 3), generator=g).float() * 0.7
        idx = cell_index(pos, 1.0, bits)
        assert torch.all((idx >= 0) & (idx < 1 << bits))
        assert torch.equal(visit_cells(visited, idx), visit_cells_ref(seen, idx))
    assert sum(len(s) for s in seen) == int(sum(bin(int(b)).count("1") for b in visited.flatten()))


def test_cell_index_is_stable_within_a_cell() -> None:
    pos = t(0.1, 0.2, 0.3, 0.9, 0.8, 0.7, 1.1, 0.2, 0.3, -0.1, 0.2, 0.3).reshape(4, 3)
    idx = cell_index(pos, 1.0, 15)
    assert int(idx[0]) == int(idx[1]) and int(idx[0]) != int(idx[2]) and int(idx[0]) != int(idx[3])
