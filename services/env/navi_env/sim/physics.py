"""Drone kinematics: body-frame velocity commands, the proximity speed limiter and contact-safe moves.

Frames: world +Z up; body +X forward, +Y left, +Z up; yaw is the rotation about +Z (counter-clockwise
seen from above is positive). Actions are `[forward, vertical, lateral, yaw_rate]` in [-1, 1].

A move never ends inside a surface. The field is 1-Lipschitz, so for a segment p -> q of length L with
clearances d(p), d(q), every point of the segment has clearance at least (d(p) + d(q) - L) / 2. A move
is accepted when it ends with d(q) >= radius and that bound is at least `path_clearance` (a positive
margin below the radius: the path provably never touches a surface, so no wall can be tunnelled), or
(escape from contact) when it ends farther from the surface than it started and the two free balls
around p and q overlap. A rejected move is bisected down to its farthest accepted fraction, then the
rest of it slides along the surface (its component into the surface removed) when that slide is
accepted too. Contact: the commanded position is closer than the radius, the drone ends closer than
the radius, or the commanded path could not be certified free (bound < 0, e.g. a thin wall between).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from navi_env.config import EnvConfig

DistanceFn = Callable[[torch.Tensor], torch.Tensor]
"""Maps points (N, 3) float32 meters to signed clearances (N,) float32 meters (positive in free space)."""

GRADIENT_STEP = 0.05
"""Central-difference step (m) for the surface normal used when sliding."""


@dataclass(frozen=True)
class Move:
    """Result of one contact-safe move of N drones."""

    position: torch.Tensor  # (N, 3) float32 world meters after the move
    clearance: torch.Tensor  # (N,) float32 clearance at `position`, meters
    contact: torch.Tensor  # (N,) bool: the commanded position was closer than the drone radius
    displacement: torch.Tensor  # (N, 3) float32 world meters actually moved


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Dot products (N,) of vectors (N, 3), summed in x, y, z order. Elementwise operations only (no
    reduction kernel, no scalar divisor, which eager CUDA turns into a reciprocal multiply), so the eager
    kernels and a torch.compile'd graph (the env's CUDA path) round every physics value identically."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def length(v: torch.Tensor) -> torch.Tensor:
    """Euclidean length (N,) of vectors (N, 3) (see `dot`)."""
    return torch.sqrt(dot(v, v))


def body_velocity(actions: torch.Tensor, config: EnvConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Clip actions (N, 4) to [-1, 1] and scale: body velocity (N, 3) m/s and yaw rate (N,) rad/s.

    The translational speed is capped at `max_speed` as a vector norm, so diagonal flight is no faster.
    """
    a = actions.clamp(-1.0, 1.0)  # (N, 4) [forward, vertical, lateral, yaw_rate]
    vel = torch.stack(
        (a[:, 0] * config.max_speed, a[:, 2] * config.max_lateral_speed, a[:, 1] * config.max_vertical_speed),
        dim=1,
    )  # (N, 3) body (x fwd, y left, z up) m/s
    limit = length(vel)[:, None].clamp_min(config.max_speed)  # (N, 1)
    vel = vel / limit * config.max_speed  # (N, 3) norm <= max_speed
    yaw_rate = a[:, 3] * config.max_yaw_rate  # (N,) rad/s
    return vel, yaw_rate


def limiter_scale(clearance: torch.Tensor, config: EnvConfig) -> torch.Tensor:
    """Proximity speed limiter (N,) in [limiter_min_fraction, 1]: 1 beyond limiter_distance, linear
    down to limiter_min_fraction at the drone radius."""
    span = config.limiter_distance - config.drone_radius
    ramp = (clearance - config.drone_radius) * (1.0 / span)  # (N,) a product: see `dot`
    return ramp.clamp(config.limiter_min_fraction, 1.0)


def body_to_world(vec: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Rotate body-frame vectors (N, 3) by yaw (N,) about +Z into the world frame (N, 3)."""
    c, s = torch.cos(yaw), torch.sin(yaw)  # (N,), (N,)
    x = c * vec[:, 0] - s * vec[:, 1]  # (N,)
    y = s * vec[:, 0] + c * vec[:, 1]  # (N,)
    return torch.stack((x, y, vec[:, 2]), dim=1)  # (N, 3)


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Wrap radians into [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2.0 * math.pi) - math.pi


def commanded_step(
    actions: torch.Tensor, clearance: torch.Tensor, yaw: torch.Tensor, config: EnvConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What actions (N, 4) ask of drones with view clearance (N,) and yaw (N,): body velocity (N, 3) m/s
    after the proximity limiter, yaw rate (N,) rad/s and the world move of one step (N, 3) meters."""
    vel, yaw_rate = body_velocity(actions, config)  # (N, 3), (N,)
    vel = vel * limiter_scale(clearance, config)[:, None]  # (N, 3) body m/s
    return vel, yaw_rate, body_to_world(vel, yaw) * config.dt


def path_bound(d0: torch.Tensor, dq: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """Lower bound (N,) of the clearance along segments with end clearances d0, dq and lengths (N,)."""
    return 0.5 * (d0 + dq - length)


def _accept(
    d0: torch.Tensor, dq: torch.Tensor, length: torch.Tensor, radius: float, path_clearance: float
) -> torch.Tensor:
    """Accept moves (N,) bool (see the module docstring)."""
    safe = (dq >= radius) & (path_bound(d0, dq, length) >= path_clearance)  # (N,) bool
    escape = (dq > d0) & (length < d0 + dq)  # (N,) bool
    return safe | escape


def surface_normal(points: torch.Tensor, distance: DistanceFn) -> torch.Tensor:
    """Unit gradient of the field at points (N, 3) by central differences: (N, 3)."""
    n = points.shape[0]
    offsets = torch.eye(3, dtype=points.dtype, device=points.device) * GRADIENT_STEP  # (3, 3)
    probes = torch.cat((points[:, None, :] + offsets, points[:, None, :] - offsets), dim=1)  # (N, 6, 3)
    d = distance(probes.reshape(n * 6, 3)).reshape(n, 6)  # (N, 6)
    grad = d[:, :3] - d[:, 3:]  # (N, 3)
    return grad / length(grad)[:, None].clamp_min(1e-9)  # (N, 3)


def safe_move(
    position: torch.Tensor,
    clearance: torch.Tensor,
    displacement: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    distance: DistanceFn,
    radius: float,
    path_clearance: float,
    iterations: int,
) -> Move:
    """Move drones at `position` (N, 3) with clearance (N,) by `displacement` (N, 3), kept in [lo, hi]
    (N, 3) each; never into a surface (see the module docstring). Fixed work per call, no host sync."""
    target = torch.minimum(torch.maximum(position + displacement, lo), hi)  # (N, 3)
    step = target - position  # (N, 3)
    full = length(step)  # (N,)
    d_target = distance(target)  # (N,)
    ok = _accept(clearance, d_target, full, radius, path_clearance)  # (N,) bool
    t_lo = ok.to(position.dtype)  # (N,) farthest accepted fraction
    d_lo = torch.where(ok, d_target, clearance)  # (N,) clearance there
    t_hi = torch.ones_like(t_lo)  # (N,)
    for _ in range(iterations):
        mid = 0.5 * (t_lo + t_hi)  # (N,)
        d_mid = distance(position + mid[:, None] * step)  # (N,)
        good = _accept(clearance, d_mid, mid * full, radius, path_clearance) & ~ok  # (N,) bool
        t_lo = torch.where(good, mid, t_lo)
        d_lo = torch.where(good, d_mid, d_lo)
        t_hi = torch.where(good | ok, t_hi, mid)
    stop = position + t_lo[:, None] * step  # (N, 3)
    rest = target - stop  # (N, 3)
    normal = surface_normal(stop, distance)  # (N, 3)
    into = dot(rest, normal)[:, None].clamp_max(0.0)  # (N, 1) <= 0
    slide_to = torch.minimum(torch.maximum(stop + rest - into * normal, lo), hi)  # (N, 3)
    d_slide = distance(slide_to)  # (N,)
    slid = _accept(d_lo, d_slide, length(slide_to - stop), radius, path_clearance) & ~ok  # (N,) bool
    final = torch.where(slid[:, None], slide_to, stop)  # (N, 3)
    d_final = torch.where(slid, d_slide, d_lo)  # (N,)
    blocked_path = path_bound(clearance, d_target, full) < 0.0  # (N,) bool
    contact = (d_target < radius) | (d_final < radius) | blocked_path  # (N,) bool
    return Move(position=final, clearance=d_final, contact=contact, displacement=final - position)


def safe_move_ref(
    position: torch.Tensor,
    clearance: torch.Tensor,
    displacement: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    distance: DistanceFn,
    radius: float,
    path_clearance: float,
    iterations: int,
) -> Move:
    """Slow twin of `safe_move`: one drone at a time with Python floats, written as the docstring reads."""

    def dist(p: list[float]) -> float:
        return float(distance(torch.tensor([p], dtype=position.dtype, device=position.device))[0])

    def accept(d0: float, dq: float, length: float) -> bool:
        safe = dq >= radius and 0.5 * (d0 + dq - length) >= path_clearance
        return safe or (dq > d0 and length < d0 + dq)

    out_p, out_d, out_c = [], [], []
    for i in range(position.shape[0]):
        p = [float(v) for v in position[i]]
        d0 = float(clearance[i])
        q = [min(max(p[k] + float(displacement[i, k]), float(lo[i, k])), float(hi[i, k])) for k in range(3)]
        step = [q[k] - p[k] for k in range(3)]
        full = math.sqrt(sum(v * v for v in step))
        dq = dist(q)
        if accept(d0, dq, full):
            out_p.append(q)
            out_d.append(dq)
            out_c.append(dq < radius or 0.5 * (d0 + dq - full) < 0.0)
            continue
        t_lo, t_hi, d_lo = 0.0, 1.0, d0
        for _ in range(iterations):
            mid = 0.5 * (t_lo + t_hi)
            d_mid = dist([p[k] + mid * step[k] for k in range(3)])
            if accept(d0, d_mid, mid * full):
                t_lo, d_lo = mid, d_mid
            else:
                t_hi = mid
        stop = [p[k] + t_lo * step[k] for k in range(3)]
        normal = [float(v) for v in surface_normal(torch.tensor([stop], dtype=position.dtype), distance)[0]]
        rest = [q[k] - stop[k] for k in range(3)]
        into = min(sum(rest[k] * normal[k] for k in range(3)), 0.0)
        slide = [
            min(max(stop[k] + rest[k] - into * normal[k], float(lo[i, k])), float(hi[i, k])) for k in range(3)
        ]
        d_slide = dist(slide)
        slide_len = math.sqrt(sum((slide[k] - stop[k]) ** 2 for k in range(3)))
        final, d_final = (slide, d_slide) if accept(d_lo, d_slide, slide_len) else (stop, d_lo)
        out_p.append(final)
        out_d.append(d_final)
        out_c.append(dq < radius or d_final < radius or 0.5 * (d0 + dq - full) < 0.0)
    pos = torch.tensor(out_p, dtype=position.dtype).reshape(-1, 3)  # (N, 3)
    return Move(
        position=pos,
        clearance=torch.tensor(out_d, dtype=position.dtype),  # (N,)
        contact=torch.tensor(out_c, dtype=torch.bool),  # (N,)
        displacement=pos - position.cpu(),
    )
