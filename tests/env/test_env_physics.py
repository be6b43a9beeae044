"""Kinematics: speed limits, frames, the proximity limiter and contact-safe moves (analytic fields)."""

from __future__ import annotations

import math

import torch

from navi_env.config import EnvConfig
from navi_env.sim.physics import (
    body_to_world,
    body_velocity,
    limiter_scale,
    safe_move,
    safe_move_ref,
    wrap_angle,
)

CFG = EnvConfig()
PATH = CFG.drone_radius * CFG.path_clearance_fraction


def wall_at(x0: float):  # a plane wall filling x > x0
    return lambda p: x0 - p[:, 0]


def slab(x0: float, thickness: float):  # a thin free-standing wall between x0 and x0 + thickness
    return lambda p: (p[:, 0] - (x0 + thickness / 2)).abs() - thickness / 2


def room(p: torch.Tensor) -> torch.Tensor:  # inside of a 10 m box centred at 0 with a 1 m pillar sphere
    box = 5.0 - p.abs().amax(dim=1)
    pillar = (p - torch.tensor([2.0, 0.0, 0.0])).norm(dim=1) - 1.0
    return torch.minimum(box, pillar)


def test_speed_is_capped_at_max_speed_and_actions_are_clipped() -> None:
    a = torch.tensor(
        [[1.0, 0, 0, 0], [3.0, 0, 0, 0], [1.0, 1.0, 1.0, 0], [-1.0, -1.0, -1.0, -1.0], [0, 0, 0, 0.5]]
    )
    vel, yaw_rate = body_velocity(a, CFG)
    speed = vel.norm(dim=1)
    assert torch.allclose(vel[0], torch.tensor([5.0, 0, 0]))
    assert torch.allclose(vel[1], vel[0])  # clipped to 1
    assert torch.all(speed <= CFG.max_speed + 1e-5)
    assert math.isclose(float(speed[2]), 5.0, rel_tol=1e-5)  # diagonal no faster than straight
    assert float(vel[3, 1]) < 0 and float(vel[3, 2]) < 0  # lateral -> body y, vertical -> body z
    assert math.isclose(float(yaw_rate[4]), 0.5 * CFG.max_yaw_rate, rel_tol=1e-6)
    assert math.isclose(float(yaw_rate[3]), -CFG.max_yaw_rate, rel_tol=1e-6)


def test_body_to_world_follows_yaw() -> None:
    fwd = torch.tensor([[1.0, 0.0, 0.0]] * 3)
    left = torch.tensor([[0.0, 1.0, 0.0]] * 3)
    yaw = torch.tensor([0.0, math.pi / 2, math.pi])
    assert torch.allclose(
        body_to_world(fwd, yaw), torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0]]), atol=1e-6
    )
    assert torch.allclose(
        body_to_world(left, yaw), torch.tensor([[0.0, 1, 0], [-1.0, 0, 0], [0, -1.0, 0]]), atol=1e-6
    )
    up = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    assert torch.allclose(body_to_world(up, yaw), up)
    assert torch.allclose(
        wrap_angle(torch.tensor([3 * math.pi / 2, -3 * math.pi / 2])),
        torch.tensor([-math.pi / 2, math.pi / 2]),
    )


def test_limiter_slows_near_geometry_and_never_stops() -> None:
    c = torch.tensor([10.0, CFG.limiter_distance, 1.5, CFG.drone_radius, 0.0])
    s = limiter_scale(c, CFG)
    assert float(s[0]) == 1.0 and float(s[1]) == 1.0
    assert math.isclose(float(s[3]), CFG.limiter_min_fraction, rel_tol=1e-6)
    assert math.isclose(float(s[4]), CFG.limiter_min_fraction, rel_tol=1e-6)
    assert 0.2 < float(s[2]) < 1.0
    assert torch.all(s[:-1] >= s[1:])  # monotone in clearance


def _drive(
    distance, start: torch.Tensor, disp: torch.Tensor, steps: int
) -> tuple[torch.Tensor, torch.Tensor, list[bool]]:
    pos = start.clone()
    clr = distance(pos)
    lo, hi = torch.full_like(pos, -50.0), torch.full_like(pos, 50.0)
    contacts = []
    min_clr = clr.clone()
    for _ in range(steps):
        m = safe_move(pos, clr, disp, lo, hi, distance, CFG.drone_radius, PATH, CFG.collision_iterations)
        pos, clr = m.position, m.clearance
        assert torch.allclose(distance(pos), clr)
        min_clr = torch.minimum(min_clr, clr)
        contacts.append(bool(m.contact.any()))
    return pos, min_clr, contacts


def test_drone_driven_at_a_wall_never_penetrates() -> None:
    start = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    disp = torch.tensor([[0.5, 0.0, 0.0], [0.4, 0.3, 0.0]])  # head-on and oblique, 5 m/s for 0.1 s
    pos, min_clr, contacts = _drive(wall_at(3.0), start, disp, 40)
    assert torch.all(min_clr >= CFG.drone_radius - 1e-5)
    assert torch.all(pos[:, 0] <= 3.0 - CFG.drone_radius + 1e-5)
    assert float(pos[0, 0]) > 3.0 - CFG.drone_radius - 0.05  # it did reach the wall
    assert contacts[-1]  # still pushing: contact every step, the episode goes on
    assert float(pos[1, 1]) > 5.0  # the oblique drone slides along the wall


def test_thin_wall_cannot_be_tunnelled() -> None:
    start = torch.tensor([[0.0, 0.0, 0.0]])
    pos, min_clr, contacts = _drive(slab(1.0, 0.05), start, torch.tensor([[2.0, 0.0, 0.0]]), 10)
    assert float(pos[0, 0]) < 1.0
    assert float(min_clr[0]) >= CFG.drone_radius - 1e-5
    assert any(contacts)


def test_drone_in_contact_can_escape() -> None:
    dist = wall_at(3.0)
    pos = torch.tensor([[2.85, 0.0, 0.0]])  # clearance 0.15 < radius
    m = safe_move(
        pos,
        dist(pos),
        torch.tensor([[-0.3, 0.0, 0.0]]),
        torch.full_like(pos, -50),
        torch.full_like(pos, 50),
        dist,
        CFG.drone_radius,
        PATH,
        CFG.collision_iterations,
    )
    assert torch.allclose(m.position, torch.tensor([[2.55, 0.0, 0.0]]))
    blocked = safe_move(
        pos,
        dist(pos),
        torch.tensor([[0.1, 0.0, 0.0]]),
        torch.full_like(pos, -50),
        torch.full_like(pos, 50),
        dist,
        CFG.drone_radius,
        PATH,
        CFG.collision_iterations,
    )
    assert float(blocked.position[0, 0]) <= 2.85 + 1e-6 and bool(blocked.contact[0])


def test_moves_stay_in_bounds() -> None:
    pos = torch.zeros(1, 3)
    m = safe_move(
        pos,
        torch.tensor([100.0]),
        torch.tensor([[5.0, -5.0, 0.0]]),
        torch.full_like(pos, -1.0),
        torch.full_like(pos, 1.0),
        lambda p: torch.full((p.shape[0],), 100.0),
        CFG.drone_radius,
        PATH,
        4,
    )
    assert torch.allclose(m.position, torch.tensor([[1.0, -1.0, 0.0]]))


def test_safe_move_matches_its_reference() -> None:
    g = torch.Generator().manual_seed(3)
    pos = (torch.rand(64, 3, generator=g) - 0.5) * 8.0
    pos = pos[room(pos) > 0.05]
    disp = (torch.rand(pos.shape[0], 3, generator=g) - 0.5) * 2.0
    lo, hi = torch.full_like(pos, -4.8), torch.full_like(pos, 4.8)
    fast = safe_move(pos, room(pos), disp, lo, hi, room, CFG.drone_radius, PATH, 6)
    slow = safe_move_ref(pos, room(pos), disp, lo, hi, room, CFG.drone_radius, PATH, 6)
    assert torch.allclose(fast.position, slow.position, atol=1e-5)
    assert torch.allclose(fast.clearance, slow.clearance, atol=1e-5)
    assert torch.equal(fast.contact, slow.contact)
    assert bool(fast.contact.any()) and bool((~fast.contact).any())
    assert torch.all(fast.clearance >= torch.minimum(room(pos), torch.tensor(CFG.drone_radius)) - 1e-5)
