"""Every reward term on hand-built cases: its sign and its scale."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from navi_env.config import EnvConfig
from navi_env.sim.rewards import (
    SHAPING_TERMS,
    TERMS,
    RewardInputs,
    cell_index,
    collision_term,
    escape_potential,
    exploration_term,
    foraging_term,
    proximity_term,
    reward_terms,
    shaping,
    structure_potential,
    term_bounds,
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


def test_each_task_prices_a_contact_with_its_own_weight() -> None:
    """Explore's contact costs collision_weight, point-goal's pointgoal_collision_weight; the terms and
    the documented bounds of each task use its own, and a full-speed crash in explore costs 75 novel cells."""
    contact, speed = torch.tensor([True]), t(CFG.max_speed)
    goal = replace(CFG, task="pointgoal")
    assert R.collision_weight != R.pointgoal_collision_weight
    for cfg, weight in ((CFG, R.collision_weight), (goal, R.pointgoal_collision_weight)):
        price = -weight * (R.collision_base + 1.0)
        out = collision_term(contact, speed, cfg.max_speed, R, cfg.task)
        assert math.isclose(float(out[0]), price, rel_tol=1e-6)
        assert term_bounds(cfg, 0.5)["collision"] == (price, 0.0)
    assert math.isclose(R.collision_weight * (R.collision_base + 1.0) / R.exploration_weight, 75.0)


def test_proximity_shaping_grows_toward_the_surface() -> None:
    d = R.proximity_distance
    out = proximity_term(t(2.5 * d, d, 0.5 * d, 0.0), R)
    assert float(out[0]) == 0.0 and float(out[1]) == 0.0
    assert math.isclose(float(out[2]), -R.proximity_weight * 0.25, rel_tol=1e-6)
    assert math.isclose(float(out[3]), -R.proximity_weight, rel_tol=1e-6)


def test_escape_is_potential_based_pays_for_leaving_and_charges_for_approaching() -> None:
    step = CFG.max_speed * CFG.dt
    g = R.shaping_gamma
    before, after = t(0.5, 1.0, 5.0, 6.0), t(1.0, 0.5, 6.0, 5.0)
    out = shaping(escape_potential(before, step, R), escape_potential(after, step, R), R)
    w = R.escape_weight / step
    assert math.isclose(float(out[0]), w * (g * 1.0 - 0.5), rel_tol=1e-6)  # left the wall: paid
    assert math.isclose(float(out[1]), w * (g * 0.5 - 1.0), rel_tol=1e-6)  # came closer: charged
    assert float(out[0]) > 0.0 > float(out[1])
    d = R.proximity_distance
    assert math.isclose(float(out[2]), w * (g - 1.0) * d, rel_tol=1e-6)  # in the open: only the (g-1) leak
    assert float(out[2]) == float(out[3])


def test_every_closed_loop_of_states_earns_no_net_shaping() -> None:
    """Random closed loops of (clearance, mid, front mid): escape + structure summed over the loop is
    (gamma - 1) * sum(Phi) <= 0, and exactly 0 with gamma = 1."""
    gen = torch.Generator().manual_seed(0)
    step = CFG.max_speed * CFG.dt
    for gamma in (R.shaping_gamma, 1.0):
        cfg = replace(R, shaping_gamma=gamma)
        for length in (2, 3, 10, 50):
            c = torch.rand(256, length, generator=gen) * 4.0  # (L loops, K states) meters, around d = 2 m
            mid, front = torch.rand(2, 256, length, generator=gen)
            phi_e = escape_potential(c, step, cfg)  # (L, K)
            phi_s = structure_potential(mid, front, cfg)  # (L, K)
            total = torch.zeros(256)
            for k in range(length):
                nxt = (k + 1) % length  # the loop returns to its first state
                total += shaping(phi_e[:, k], phi_e[:, nxt], cfg) + shaping(phi_s[:, k], phi_s[:, nxt], cfg)
            assert float(total.max()) <= 1e-5
            if gamma == 1.0:
                assert float(total.abs().max()) <= 1e-5


def test_exploration_pays_novel_cells_only_with_clearance() -> None:
    gate = R.exploration_min_clearance
    out = exploration_term(torch.tensor([True, True, False]), t(2 * gate, 0.8 * gate, 2 * gate), R)
    assert torch.allclose(out, t(R.exploration_weight, 0.0, 0.0))  # wall hugging earns nothing


def test_foraging_penalises_blind_and_wall_hugging_views() -> None:
    out = foraging_term(t(0.2, 1.0, 0.2), t(0.0, 0.0, 1.0), R)
    assert float(out[0]) == 0.0  # a structured view costs nothing
    assert math.isclose(float(out[1]), -R.blind_weight, rel_tol=1e-6)  # all horizon: blind
    assert math.isclose(float(out[2]), -R.near_weight, rel_tol=1e-6)  # all near field: hugging


def test_structure_rewards_gaining_structure_and_turning_toward_it() -> None:
    g = R.shaping_gamma
    phi = structure_potential(t(0.2, 0.8, 0.5, 0.5), t(0.0, 0.4, 0.2, 0.8), R)
    assert math.isclose(float(phi[0]), R.structure_weight * 0.2, rel_tol=1e-6)
    gained = shaping(phi[0:1], phi[1:2], R)  # more mid-range structure, more of it ahead
    assert float(gained) > 0.0
    turned = shaping(phi[2:3], phi[3:4], R)  # same structure, turned toward it
    assert math.isclose(
        float(turned), R.structure_front_weight * 0.6 * g - (1 - g) * float(phi[2]), rel_tol=1e-4
    )
    turned_away = shaping(phi[3:4], phi[2:3], R)
    assert float(turned_away) < 0.0


def test_existential_tax_and_terms_sum() -> None:
    z = torch.zeros(2)
    x = RewardInputs(
        contact=torch.tensor([False, True]),
        speed=t(0.0, 3.0),
        novel=torch.tensor([False, True]),
        clearance_before=t(10.0, 0.4),
        clearance=t(10.0, 0.2),
        mid_before=z,
        mid=z,
        front_mid_before=z,
        front_mid=z,
        void=t(0.0, 0.9),
        near=t(0.0, 0.4),
    )
    terms = reward_terms(x, CFG)
    assert tuple(terms) == TERMS and set(SHAPING_TERMS) <= set(TERMS)
    assert torch.allclose(terms["existential"], t(-0.02, -0.02))
    idle = sum(float(v[0]) for v in terms.values())
    leak = (R.shaping_gamma - 1) * R.escape_weight * R.proximity_distance / (CFG.max_speed * CFG.dt)
    assert math.isclose(idle, -0.02 + leak, rel_tol=1e-5)  # an idle drone in the open pays the tax (+ leak)
    assert sum(float(v[1]) for v in terms.values()) < -1.0  # a crash into a wall is strongly negative


def test_term_bounds_hold_on_random_inputs() -> None:
    """Each term of random transitions lies within term_bounds when the clearance changes by at most
    one step of flight plus a voxel."""
    gen = torch.Generator().manual_seed(1)
    n, change = 4096, CFG.max_speed * CFG.dt + 0.1
    c0 = torch.rand(n, generator=gen) * 5.0
    c1 = (c0 + (torch.rand(n, generator=gen) * 2 - 1) * change).clamp_min(0.0)
    u = torch.rand(6, n, generator=gen)
    x = RewardInputs(
        contact=u[0] < 0.3,
        speed=u[1] * CFG.max_speed,
        novel=u[2] < 0.5,
        clearance_before=c0,
        clearance=c1,
        mid_before=u[3],
        mid=u[4],
        front_mid_before=u[5],
        front_mid=u[3] * u[4],
        void=u[0],
        near=u[1],
    )
    bounds = term_bounds(CFG, change)
    for name, value in reward_terms(x, CFG).items():
        lo, hi = bounds[name]
        assert float(value.min()) >= lo - 1e-5 and float(value.max()) <= hi + 1e-5, name


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
