"""Scripted moving obstacles of the drone env: placement at episode start, one move per step, and the
sweep that stops an obstacle at a drone instead of letting it pass through.

Every actor has a world of its own with K obstacle slots: `ObstacleState.prims` (N, K, 16) are the
records the tracer and `sample_distance` read (navi_env.tracer.primitives), so actor b's rays and physics see
its obstacles and nobody else's, and a pose update is a tensor write (nothing is rebuilt).

One step, before the drone moves (docs/SIMULATION.md, "Moving obstacles"):
  target   linear: back and forth along a segment (reach = half length); circular: round a horizontal
           circle of radius reach; random walk: the heading turns a little every step, and points home
           when the next position would leave the leash (reach) around the start
  walls    the centre marches along its path c0 -> c1 by (d - bound - WALL_SKIN) / L, d the static
           clearance: the field is 1-Lipschitz, so the bounding sphere stays free all the way; an
           obstacle stopped short by a wall turns back
  sweep    the obstacle's translation c0 -> c1 is marched against the drone: the drone centre relative
           to the obstacle moves along p - c0 - t (c1 - c0), and with the exact primitive distance f the
           march advances t by (f - drone_radius - SKIN) / L. f is 1-Lipschitz in the point, so f never
           drops below the drone radius on the way: however fast or thin the obstacle, it stops at the
           drone, never passes through it. Primitives are convex, so f is convex in t: an obstacle that
           is not approaching at the start of the step moves freely. Stopped by the drone within TOUCH of its sphere is a collision; the
           obstacle then turns back (an obstacle held by a wall does not hit anyone).
Letters: N actors, K slots per actor, T placement tries.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TypeVar, cast

import torch

from navi_env.config import OBSTACLE_MOTIONS, ObstacleConfig
from navi_env.sim import rng
from navi_env.sim.episodes import SpawnTable, pick_index
from navi_env.tracer import primitives as ob
from navi_env.tracer import trace

LINEAR, CIRCULAR, RANDOM_WALK = 0, 1, 2
SHAPE_KIND = {"sphere": ob.SPHERE, "capsule": ob.CAPSULE, "box": ob.BOX, "obb": ob.OBB}
TOUCH = 0.02
"""An obstacle stopped within this (m) of the drone's sphere touches it: a collision."""
WALL_SKIN = 0.01
"""The wall march stops an obstacle's bounding sphere this far (m) from the static surface (the
trilinear field's slope can exceed 1 by a little, so a march to 0 could end a few mm inside)."""
CREEP = 0.001
"""An obstacle that starts closer to a wall than WALL_SKIN may lose this much (m) of clearance in a step:
enough for its march to leave the wall again (convergence is geometric), too little to enter it."""
SKIN = 0.005
"""The sweep stops an obstacle this far (m) outside the drone's sphere (float32 rounding never puts the
drone inside)."""
PLACE_MARGIN = 0.05
"""Extra static clearance (m) an obstacle's bounding sphere needs at its starting point."""

SCENE_KEYS: tuple[str, ...] = (
    "count",
    "size_min",
    "size_max",
    "speed_min",
    "speed_max",
    "reach_min",
    "reach_max",
)
"""ObstacleConfig fields a scene may declare for itself (sidecar / corpus manifest "obstacles")."""

_T = TypeVar("_T")
StaticFn = Callable[[torch.Tensor], torch.Tensor]
"""Static clearance (N*K,) at points (N*K, 3) in actor-major order (each actor's scene)."""


@dataclass(frozen=True)
class ObstacleState:
    """Device tensors of N actors' K obstacles, allocated once and written in place."""

    prims: torch.Tensor  # (N, K, 16) float32 records (kind none: an empty slot)
    anchor: torch.Tensor  # (N, K, 3) float32 segment middle, circle centre or leash centre, m
    axis: torch.Tensor  # (N, K, 3) float32 unit: segment direction, circle's e1 or walk heading
    phase: torch.Tensor  # (N, K) float32 offset along the segment (m) or angle on the circle (rad)
    speed: torch.Tensor  # (N, K) float32 signed m/s
    reach: torch.Tensor  # (N, K) float32 half segment, circle radius or leash, m
    bound: torch.Tensor  # (N, K) float32 bounding radius about the centre, m
    clearance: torch.Tensor  # (N, K) float32 lower bound of the static clearance at the centre, m
    shape: torch.Tensor  # (K,) int64 primitive kind per slot
    motion: torch.Tensor  # (K,) int64 LINEAR / CIRCULAR / RANDOM_WALK per slot

    @property
    def count(self) -> int:
        """K: slots per actor."""
        return int(self.prims.shape[1])


@dataclass(frozen=True)
class SceneObstacles:
    """Per-scene obstacle settings (S,) on the device: the env's ObstacleConfig where a scene declares
    nothing, the scene's own values where it does."""

    count: torch.Tensor  # (S,) int64 active slots in the scene (<= K)
    size_min: torch.Tensor  # (S,) float32 m
    size_max: torch.Tensor  # (S,) float32 m
    speed_min: torch.Tensor  # (S,) float32 m/s
    speed_max: torch.Tensor  # (S,) float32 m/s
    reach_min: torch.Tensor  # (S,) float32 m
    reach_max: torch.Tensor  # (S,) float32 m

    @property
    def slots(self) -> int:
        """K: slots every actor needs (the largest count)."""
        return int(self.count.max()) if self.count.numel() else 0


def scene_obstacles(
    cfg: ObstacleConfig, declared: Sequence[Mapping[str, float]], names: Sequence[str], device: torch.device
) -> SceneObstacles:
    """Merge each scene's declaration (a mapping of SCENE_KEYS, possibly empty) over `cfg`; every merged
    setting is validated by ObstacleConfig. Raises ValueError naming the scene on a bad declaration."""
    merged = []
    for name, decl in zip(names, declared, strict=True):
        unknown = sorted(set(decl) - set(SCENE_KEYS))
        if unknown:
            raise ValueError(
                f"scene {name!r} declares unknown obstacle settings {unknown}; known: {SCENE_KEYS}"
            )
        try:
            values = {k: (int(v) if k == "count" else float(v)) for k, v in decl.items()}
            merged.append(replace(cfg, **values))  # type: ignore[arg-type]
        except (TypeError, ValueError) as err:
            raise ValueError(f"scene {name!r}: bad obstacle declaration {dict(decl)}: {err}") from err

    def col(key: str, dtype: torch.dtype) -> torch.Tensor:
        return torch.tensor([getattr(m, key) for m in merged], dtype=dtype, device=device)  # (S,)

    return SceneObstacles(
        count=col("count", torch.int64),
        **{k: col(k, torch.float32) for k in SCENE_KEYS if k != "count"},
    )


def allocate(
    n: int,
    cfg: ObstacleConfig,
    device: torch.device,
    slots: int | None = None,
    records: torch.Tensor | None = None,
) -> ObstacleState:
    """Empty slots for N actors (kinds and motions cycle through cfg.shapes and cfg.motions); K = `slots`
    (default cfg.count). `records` (N, K, 16), a view into a larger record tensor, holds the records."""
    k = cfg.count if slots is None else slots
    shape = torch.tensor([SHAPE_KIND[cfg.shapes[i % len(cfg.shapes)]] for i in range(k)], dtype=torch.int64)
    motion = torch.tensor(
        [OBSTACLE_MOTIONS.index(cfg.motions[i % len(cfg.motions)]) for i in range(k)], dtype=torch.int64
    )

    def f32(*shape_: int) -> torch.Tensor:
        return torch.zeros(*shape_, dtype=torch.float32, device=device)

    return ObstacleState(
        prims=f32(n, k, ob.WORDS) if records is None else records,
        anchor=f32(n, k, 3),
        axis=f32(n, k, 3),
        phase=f32(n, k),
        speed=f32(n, k),
        reach=f32(n, k),
        bound=f32(n, k),
        clearance=f32(n, k),
        shape=shape.to(device),
        motion=motion.to(device),
    )


def _unit(v: torch.Tensor) -> torch.Tensor:
    """v (..., 3) scaled to unit length (a zero vector stays zero)."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def place(
    state: ObstacleState,
    mask: torch.Tensor,
    spawns: SpawnTable,
    scene: torch.Tensor,
    origin: torch.Tensor,
    drone_radius: float,
    cfg: ObstacleConfig,
    table: SceneObstacles,
    seed: torch.Tensor,
    tick: torch.Tensor,
    actor: torch.Tensor,
    fused: bool = False,
) -> None:
    """New obstacles for the actors with `mask` (N,) bool, whose drones start at origin (N, 3) in
    `scene` (N,): the first table.count[scene] slots each try cfg.place_tries spawn points of the scene
    and take the first whose static clearance holds the obstacle's bounding sphere and whose distance
    from the drone lies in [max(place_min, bound + drone radius), place_max]; a slot with no such point,
    or past the scene's count, stays empty. Sizes, speeds and reaches come from the scene's table row.
    `fused`: as one compiled pass (see advance)."""
    if fused:  # this function's compiled twin (which runs with fused=False)
        _call(place, True, state, mask, spawns, scene, origin, drone_radius, cfg, table, seed, tick, actor)
        return
    n, k, t = state.prims.shape[0], state.count, cfg.place_tries
    dev = state.prims.device
    slot = torch.arange(k, dtype=torch.int64, device=dev)  # (K,)
    tries = torch.arange(t, dtype=torch.int64, device=dev)  # (T,)
    key = (actor[:, None, None] * k + slot[None, :, None]) * t + tries[None, None, :]  # (N, K, T)
    u_pick = rng.uniform(seed, rng.STREAM_OBSTACLE_PLACE, tick, key)  # (N, K, T)
    idx = pick_index(u_pick, spawns.count[scene][:, None, None].expand(n, k, t))  # (N, K, T)
    rows = scene[:, None, None].expand(n, k, t)  # (N, K, T)
    cand = spawns.position[rows, idx]  # (N, K, T, 3)
    cand_clear = spawns.clearance[rows, idx]  # (N, K, T)

    # 16 numbers per slot, drawn in two batched hashes (number q of a slot has key base + q)
    words = ((actor[:, None] * k + slot[None, :]) * 16)[..., None] + torch.arange(
        16, device=dev
    )  # (N, K, 16)
    u_all = rng.uniform(seed, rng.STREAM_OBSTACLE_SHAPE, tick, words)  # (N, K, 16) in [0, 1)
    g_all = rng.normal(seed, rng.STREAM_OBSTACLE_SHAPE, tick, words[..., 5:12])  # (N, K, 7) numbers 5..11

    def u(q: int) -> torch.Tensor:
        return u_all[..., q]  # (N, K) in [0, 1)

    def g(q: int) -> torch.Tensor:
        return g_all[..., q - 5]  # (N, K) standard normal

    def span(lo: torch.Tensor, hi: torch.Tensor, q: int) -> torch.Tensor:
        return lo[scene][:, None] + (hi - lo)[scene][:, None] * u(
            q
        )  # (N, K) uniform in [lo, hi] of the scene

    size = torch.stack([span(table.size_min, table.size_max, q) for q in range(3)], dim=-1)  # (N, K, 3)
    kind = state.shape[None, :].expand(n, k).to(torch.float32)  # (N, K)
    azimuth = 2.0 * math.pi * u(3)  # (N, K)
    tilt = 0.3 * (2.0 * u(4) - 1.0)  # (N, K) mostly horizontal paths
    heading = _unit(torch.stack((torch.cos(azimuth), torch.sin(azimuth), tilt), dim=-1))  # (N, K, 3)
    flat = torch.stack((torch.cos(azimuth), torch.sin(azimuth), torch.zeros_like(azimuth)), dim=-1)
    capsule_dir = _unit(torch.stack((g(5), g(6), g(7)), dim=-1))  # (N, K, 3)
    quat = torch.stack((g(8), g(9), g(10), g(11)), dim=-1)  # (N, K, 4)
    quat = quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    speed = span(table.speed_min, table.speed_max, 12)  # (N, K)
    speed = torch.where(u(13) < 0.5, -speed, speed)
    reach = span(table.reach_min, table.reach_max, 14)  # (N, K)

    rec = torch.zeros(n, k, ob.WORDS, dtype=torch.float32, device=dev)  # (N, K, 16)
    rec[..., ob.KIND] = kind
    rec[..., ob.CLASS] = float(cfg.semantic_class)
    rec[..., ob.OWNER] = ob.NO_OWNER
    rec[..., ob.RADIUS] = size[..., 0]
    is_capsule = (state.shape == ob.CAPSULE)[None, :, None]  # (1, K, 1)
    rec[..., ob.AXIS : ob.AXIS + 3] = torch.where(is_capsule, capsule_dir * size[..., 1:2], size)
    rec[..., ob.QUAT : ob.QUAT + 4] = torch.where((state.shape == ob.OBB)[None, :, None], quat, 0.0)
    rec[..., ob.QUAT] = torch.where(state.shape[None, :] == ob.OBB, rec[..., ob.QUAT], 1.0)
    bound = ob.bounding_radius(rec)  # (N, K)

    far = (cand - origin[:, None, None, :]).norm(dim=-1)  # (N, K, T)
    near_limit = torch.clamp_min(bound + drone_radius + PLACE_MARGIN, cfg.place_min)[..., None]  # (N, K, 1)
    ok = (cand_clear >= bound[..., None] + PLACE_MARGIN) & (far >= near_limit) & (far <= cfg.place_max)
    found = ok.any(dim=-1) & (slot[None, :] < table.count[scene][:, None])  # (N, K) bool
    first = ok.to(torch.int8).argmax(dim=-1, keepdim=True)  # (N, K, 1) first valid try
    center = cand.gather(2, first[..., None].expand(n, k, 1, 3))[:, :, 0]  # (N, K, 3)
    clear = cand_clear.gather(2, first)[..., 0]  # (N, K)
    rec[..., ob.KIND] = torch.where(found, kind, float(ob.NONE))
    rec[..., ob.CENTER : ob.CENTER + 3] = center

    circular = (state.motion == CIRCULAR)[None, :, None]  # (1, K, 1)
    axis = torch.where(circular, flat, heading)  # (N, K, 3)
    anchor = torch.where(circular, center - reach[..., None] * flat, center)  # (N, K, 3) start at phase 0

    m = mask[:, None]  # (N, 1)
    m3 = mask[:, None, None]  # (N, 1, 1)
    state.prims.copy_(torch.where(m3, rec, state.prims))
    state.anchor.copy_(torch.where(m3, anchor, state.anchor))
    state.axis.copy_(torch.where(m3, axis, state.axis))
    state.phase.copy_(torch.where(m, torch.zeros_like(speed), state.phase))
    state.speed.copy_(torch.where(m, speed, state.speed))
    state.reach.copy_(torch.where(m, reach, state.reach))
    state.bound.copy_(torch.where(m, bound, state.bound))
    state.clearance.copy_(torch.where(m, clear, state.clearance))


def _plan(
    state: ObstacleState,
    dt: float,
    walk_turn: float,
    seed: torch.Tensor,
    tick: torch.Tensor,
    actor: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """advance, first part: where each obstacle's script takes it this step. Returns the start centres c0
    (N, K, 3), the translation delta to the target (N, K, 3), its length (N, K), the wall march's floor
    (N, K), and the script's new phase (N, K) and axis (N, K, 3) (the random walk's new heading)."""
    n, k = state.phase.shape
    c0 = state.prims[..., ob.CENTER : ob.CENTER + 3].clone()  # (N, K, 3): the commit moves the records
    reach, speed = state.reach, state.speed  # (N, K)
    s_lin = (state.phase + speed * dt).clamp(-reach, reach)  # (N, K)
    p_lin = state.anchor + s_lin[..., None] * state.axis  # (N, K, 3)
    angle = state.phase + speed / reach.clamp_min(1e-6) * dt  # (N, K)
    e1 = state.axis  # (N, K, 3) horizontal
    e2 = torch.stack((-e1[..., 1], e1[..., 0], torch.zeros_like(e1[..., 0])), dim=-1)  # (N, K, 3)
    p_circ = state.anchor + reach[..., None] * (
        torch.cos(angle)[..., None] * e1 + torch.sin(angle)[..., None] * e2
    )  # (N, K, 3)
    key = ((actor[:, None] * k + torch.arange(k, device=actor.device)[None, :]) * 3)[
        ..., None
    ] + torch.arange(3, device=actor.device)  # (N, K, 3)
    noise = rng.normal(seed, rng.STREAM_OBSTACLE_WALK, tick, key)  # (N, K, 3)
    noise = torch.stack((noise[..., 0], noise[..., 1], 0.3 * noise[..., 2]), dim=-1)  # mostly horizontal
    heading = _unit(state.axis + walk_turn * noise)  # (N, K, 3)
    step = speed.abs()[..., None] * dt  # (N, K, 1)
    leaving = (c0 + step * heading - state.anchor).norm(dim=-1) > reach  # (N, K) bool
    heading = torch.where(leaving[..., None], _unit(state.anchor - c0), heading)  # (N, K, 3)
    p_walk = c0 + step * heading  # (N, K, 3)
    motion = state.motion[None, :].expand(n, k)  # (N, K)
    target = torch.where(
        (motion == LINEAR)[..., None], p_lin, torch.where((motion == CIRCULAR)[..., None], p_circ, p_walk)
    )  # (N, K, 3)
    phase = torch.where(
        motion == LINEAR, s_lin, torch.where(motion == CIRCULAR, angle, state.phase)
    )  # (N, K)
    axis = torch.where((motion == RANDOM_WALK)[..., None], heading, state.axis)  # (N, K, 3)
    delta = target - c0  # (N, K, 3)
    length = delta.norm(dim=-1).clamp_min(1e-9)  # (N, K)
    floor = torch.minimum(state.bound + WALL_SKIN, state.clearance - CREEP)  # (N, K)
    return c0, delta, length, floor, phase, axis


def sweep(
    rec: torch.Tensor, delta: torch.Tensor, drone: torch.Tensor, radius: float, iterations: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """How far each obstacle (N, K, 16 records at their start) may translate by delta (N, K, 3) before it
    would come within SKIN of a drone sphere of `radius` at drone (N, 3): fraction t (N, K) in [0, 1], and the
    obstacle's distance from the drone centre there (N, K). Conservative march (module docstring), one
    launch of the tracer library (CPU threads or CUDA); `sweep_ref` is its torch twin."""
    return trace.sweep_prims(
        rec.contiguous(), delta.contiguous(), drone.contiguous(), radius, SKIN, iterations
    )


def sweep_ref(
    rec: torch.Tensor, delta: torch.Tensor, drone: torch.Tensor, radius: float, iterations: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """`sweep` in torch ops (about 60 kernels per march step on a GPU): the same march, for parity."""
    length = delta.norm(dim=-1).clamp_min(1e-9)  # (N, K)
    rel = drone[:, None, :]  # (N, 1, 3)
    # Every primitive is convex, so f(t) = distance(drone, obstacle moved by t delta) is convex in t: an
    # obstacle that does not approach at t = 0 never does on this step, and may move all the way.
    probe = (1e-3 / length).clamp_max(1.0)  # (N, K) a millimetre along the path
    f0 = ob.distance(rec, rel)  # (N, K)
    leaving = ob.distance(rec, rel - probe[..., None] * delta) >= f0  # (N, K) bool
    t = torch.zeros_like(length)  # (N, K)
    for _ in range(iterations):
        gap = ob.distance(rec, rel - t[..., None] * delta) - radius - SKIN  # (N, K)
        t = (t + gap.clamp_min(0.0) / length).clamp_max(1.0)
    t = torch.where(leaving, torch.ones_like(t), t)
    return t, ob.distance(rec, rel - t[..., None] * delta)


def advance(
    state: ObstacleState,
    static: StaticFn,
    drone: torch.Tensor,
    radius: float,
    dt: float,
    cfg: ObstacleConfig,
    seed: torch.Tensor,
    tick: torch.Tensor,
    actor: torch.Tensor,
    fused: bool = False,
) -> torch.Tensor:
    """Move every obstacle one step (module docstring); returns (N,) bool: an obstacle ran into the
    drone at drone (N, 3) this step. Fixed work, no host sync. `fused`: run the elementwise parts as
    torch.compile'd passes (CUDA; same arithmetic, a few kernels instead of about 200)."""
    n, k = state.phase.shape
    c0, delta, length, floor, phase, axis = _call(_plan, fused, state, dt, cfg.walk_turn, seed, tick, actor)

    def static_at(t: torch.Tensor) -> torch.Tensor:
        return static((c0 + t[..., None] * delta).reshape(n * k, 3)).reshape(n, k)  # (N, K)

    # walls: march the bounding sphere's centre along its path; every point up to t_wall keeps it free
    t_wall, d = torch.zeros_like(length), state.clearance  # (N, K), (N, K) sampled at c0
    for _ in range(cfg.wall_iterations):
        t_wall = (t_wall + (d - floor).clamp_min(0.0) / length).clamp_max(1.0)
        d = static_at(t_wall)
    t_drone, reach_d = sweep(state.prims, delta, drone, radius, cfg.sweep_iterations)  # (N, K), (N, K)
    t, touch = _call(_commit, fused, state, c0, delta, t_wall, t_drone, reach_d, phase, axis, radius)
    state.clearance.copy_(torch.where(t == t_wall, d, static_at(t)))
    return touch.any(dim=1)


def _commit(
    state: ObstacleState,
    c0: torch.Tensor,
    delta: torch.Tensor,
    t_wall: torch.Tensor,
    t_drone: torch.Tensor,
    reach_d: torch.Tensor,
    phase: torch.Tensor,
    axis: torch.Tensor,
    radius: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """advance, last part: move each obstacle by the fraction t (N, K) its walls and the drone allow and
    update its script; returns t and touch (N, K) bool: stopped by the drone within TOUCH of it."""
    rec = state.prims  # (N, K, 16)
    active = rec[..., ob.KIND] != ob.NONE  # (N, K) bool
    t = torch.where(active, torch.minimum(t_wall, t_drone), torch.zeros_like(t_wall))  # (N, K)
    touch = active & (t_drone < t_wall) & (reach_d - radius <= TOUCH)  # (N, K) bool: stopped by the drone
    partial = t < 1.0  # (N, K) bool: stopped by a wall or the drone
    at_end = (state.motion[None, :] == LINEAR) & (phase.abs() >= state.reach)  # (N, K) bool
    turn = active & (partial | at_end)  # (N, K) bool
    rec[..., ob.CENTER : ob.CENTER + 3] = c0 + t[..., None] * delta
    state.phase.copy_(state.phase + t * (phase - state.phase))
    state.axis.copy_(
        torch.where(partial[..., None] & (state.motion[None, :, None] == RANDOM_WALK), -axis, axis)
    )
    state.speed.copy_(torch.where(turn, -state.speed, state.speed))
    return t, touch


_Fn = TypeVar("_Fn", bound=Callable[..., object])


@functools.cache
def _compiled(fn: _Fn) -> _Fn:
    """fn compiled once per process (shapes specialised first, dynamic once a second env size appears;
    not fullgraph, so past dynamo's recompile limit it runs eagerly instead of failing)."""
    return cast(_Fn, torch.compile(fn))


def _call(fn: Callable[..., _T], fused: bool, *args: object) -> _T:
    """fn(*args), through its compiled twin when `fused` (compiled on the first call: make that call
    before recording a CUDA graph)."""
    if not fused:
        return fn(*args)
    with torch.no_grad():  # one grad mode for every call: the compiled code is never re-specialised
        return _compiled(fn)(*args)


def obstacle_distance(state: ObstacleState, points: torch.Tensor, fused: bool = False) -> torch.Tensor:
    """Distance (N,) from each actor's point (N, 3) to the nearest of its obstacles (+inf with none);
    `fused`: one compiled pass (see advance)."""
    return _call(_nearest, fused, state.prims, points)


def _nearest(prims: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    return ob.distance(prims, points[:, None, :]).amin(dim=1)  # (N,)
