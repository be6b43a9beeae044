"""The baselines every trained drone is compared with: `random` and the scripted `reactive` avoider; for
point-goal episodes also `greedy` (straight at the goal mark, with the avoider, no map) and `oracle`
(along the true shortest path from the env's map, with the avoider: the ceiling).

Both act on the same observation as the trained policy (channel 0 of the DistanceMatrix, depth /
horizon, azimuth bin 0 straight ahead and increasing to the left, elevation from bottom to top) and
are deterministic for a given seed. docs/TRAINING.md describes the reactive algorithm.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Protocol

import torch
import torch.nn.functional as F

from navi_learner.engine.heads import ACTION_DIM
from navi_learner.envs.protocol import capabilities


class EvalPolicy(Protocol):
    """A policy the evaluator can drive."""

    name: str

    def reset(self, n: int, device: torch.device) -> None:
        """Prepare for n actors."""
        ...

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        """obs (N, 3, Az, El), resets (N,) bool -> actions (N, 4) in [-1, 1]."""
        ...


class RandomPolicy:
    """Uniform actions in [-1, 1]^4 from a seeded generator."""

    name = "random"

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed
        self.gen: torch.Generator | None = None

    def reset(self, n: int, device: torch.device) -> None:
        self.gen = torch.Generator(device=device).manual_seed(self.seed)

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        n = obs.shape[0]
        return torch.rand(n, ACTION_DIM, generator=self.gen, device=obs.device) * 2 - 1  # (N, 4)


@dataclass(frozen=True)
class ReactiveConfig:
    """Distances in meters, angles in degrees."""

    horizon: float = 100.0
    """Depth that channel 0 = 1 stands for (EnvConfig.horizon)."""
    elevation_min: float = -90.0
    """Elevation of the ray pattern's lowest edge (SensorConfig.elevation_min_deg)."""
    elevation_max: float = 90.0
    """Elevation of the ray pattern's highest edge (SensorConfig.elevation_max_deg)."""
    band: float = 30.0
    """Rays within +-band of the horizontal plane decide where the drone can fly."""
    body_half_angle: float = 10.0
    """A heading is as free as the nearest surface within +-this azimuth of it (the drone's width)."""
    open_cap: float = 30.0
    """Free distances beyond this count as equally open (m)."""
    ahead_preference: float = 3.0
    """Meters of free distance a heading straight ahead is worth over one straight behind."""
    stop_distance: float = 0.8
    """Forward speed is zero when the free distance ahead is this or less (m): the drone radius (0.3 m)
    plus one step of full-speed flight (0.5 m)."""
    brake_distance: float = 3.0
    """Forward speed ramps from zero at stop_distance to full at stop_distance + brake_distance (m): the
    env's speed limiter distance."""
    side_distance: float = 2.5
    """Surfaces closer than this to the side or above/below push the drone away (m)."""
    turn_angle: float = 60.0
    """Heading error that commands the full yaw rate."""


class ReactivePolicy:
    """Scripted avoider: gap following with a speed governor.

    1. Free distance per azimuth: the nearest surface among the rays within +-band of the horizontal
       plane, then the minimum over +-body_half_angle of azimuth (a gap must fit the drone).
    2. Heading: the azimuth with the largest min(free, open_cap) + ahead_preference * (1 + cos) / 2,
       so the drone keeps going straight unless another gap is clearly more open; yaw toward it.
    3. Speed governor: forward speed from the free distance straight ahead (zero at stop_distance,
       full at stop_distance + brake_distance) times the cosine of the heading error.
    4. Lateral and vertical: move away from the nearer side (left / right within +-30 degrees of the
       side, above / below beyond +-40 degrees of elevation) when a surface is within side_distance.
    """

    name = "reactive"

    def __init__(self, cfg: ReactiveConfig | None = None) -> None:
        self.cfg = cfg or ReactiveConfig()

    def reset(self, n: int, device: torch.device) -> None:
        return None

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        cfg = self.cfg
        near = surroundings(obs, cfg)
        ahead_bonus = cfg.ahead_preference * 0.5 * (1.0 + torch.cos(torch.deg2rad(near.azimuth)))  # (Az,)
        best = (near.wide.clamp(max=cfg.open_cap) + ahead_bonus).argmax(dim=1)  # (N,)
        error = near.azimuth[best]  # (N,) degrees, left positive
        yaw = (error / cfg.turn_angle).clamp(-1.0, 1.0)  # (N,)
        governor = ((near.wide[:, 0] - cfg.stop_distance) / cfg.brake_distance).clamp(0.0, 1.0)  # (N,)
        forward = governor * torch.cos(torch.deg2rad(error)).clamp(min=0.0)  # (N,)
        return torch.stack(
            [forward, near.vertical.clamp(-1.0, 1.0), near.lateral.clamp(-1.0, 1.0), yaw], dim=1
        )  # (N, 4)


@dataclass(frozen=True)
class Surroundings:
    """What the scripted policies read from an observation (ReactivePolicy's steps 1 and 4)."""

    elevation: torch.Tensor  # (El,) degrees of each elevation bin
    azimuth: torch.Tensor  # (Az,) degrees of each azimuth bin in (-180, 180], left positive
    wide: torch.Tensor  # (N, Az) free distance per heading, the drone's width included, meters
    lateral: torch.Tensor  # (N,) push away from the nearer side, + to the left, in [-1, 1]
    vertical: torch.Tensor  # (N,) push away from the nearer of floor and ceiling, + climbs, in [-1, 1]


def surroundings(obs: torch.Tensor, cfg: ReactiveConfig) -> Surroundings:
    """Free distance per heading and the side pushes of observations obs (N, 3, Az, El)."""
    depth = obs[:, 0].float() * cfg.horizon  # (N, Az, El) meters
    n, az, el = depth.shape
    dev = depth.device
    elevation = cfg.elevation_min + (torch.arange(el, device=dev) + 0.5) * (
        (cfg.elevation_max - cfg.elevation_min) / el
    )  # (El,) degrees
    azimuth = torch.remainder(torch.arange(az, device=dev) * (360.0 / az) + 180.0, 360.0) - 180.0  # (Az,)
    band = elevation.abs() <= cfg.band  # (El,) bool
    free = depth[:, :, band].amin(dim=2) if bool(band.any()) else depth.amin(dim=2)  # (N, Az)
    k = max(0, round(cfg.body_half_angle * az / 360.0))
    wide = -F.max_pool1d(F.pad(-free[:, None], (k, k), mode="circular"), 2 * k + 1, stride=1)[:, 0]  # (N, Az)

    def side(lo: float, hi: float) -> torch.Tensor:
        mask = (azimuth >= lo) & (azimuth <= hi)  # (Az,) bool
        return wide[:, mask].amin(dim=1).clamp(max=cfg.side_distance)  # (N,)

    def cone(mask: torch.Tensor) -> torch.Tensor:
        if not bool(mask.any()):
            return torch.full((n,), cfg.side_distance, device=dev)
        return depth[:, :, mask].amin(dim=(1, 2)).clamp(max=cfg.side_distance)  # (N,)

    lateral = (side(60.0, 120.0) - side(-120.0, -60.0)) / cfg.side_distance  # (N,)
    vertical = (cone(elevation >= 40.0) - cone(elevation <= -40.0)) / cfg.side_distance  # (N,)
    return Surroundings(elevation, azimuth, wide, lateral, vertical)


def reactive_for(horizon: float, elevation_min: float, elevation_max: float) -> ReactivePolicy:
    """The reactive baseline for an environment's horizon and ray pattern."""
    return ReactivePolicy(
        ReactiveConfig(horizon=horizon, elevation_min=elevation_min, elevation_max=elevation_max)
    )


def reactive_for_env(env: object) -> ReactivePolicy:
    """The reactive baseline tuned to an env's capabilities: its horizon and ray pattern (the drone env),
    its horizon over every elevation (the toy env), or the defaults."""
    caps = capabilities(env)
    if caps.horizon is None:
        return ReactivePolicy()
    low, high = caps.elevation_deg or (-90.0, 90.0)
    return reactive_for(caps.horizon, low, high)


@dataclass(frozen=True)
class GoalSeekerConfig:
    """The point-goal baselines' controller: the reactive avoider's gap choice, pulled toward the goal."""

    avoid: ReactiveConfig = ReactiveConfig()
    """Horizon, ray pattern and avoidance distances (the reactive baseline's)."""
    goal_preference: float = 12.0
    """Meters of free distance a heading straight at the goal is worth over one straight away from it."""
    approach_distance: float = 2.5
    """Forward speed ramps down linearly within this distance (m) of the goal, to 10% at the goal."""
    climb_distance: float = 1.0
    """Vertical action is the goal's height difference over this (m), clamped to [-1, 1]."""


class GoalSeekerPolicy(ABC):
    """A point-goal controller for a goal direction and distance per actor (`goal(obs)`): the free
    distance per azimuth as the reactive avoider reads it, the heading with the largest
    min(free, distance + 1 m) + goal_preference * (1 + cos(angle to the goal)) / 2, yaw toward it; forward
    speed from the avoider's governor, the cosine of the heading error and the approach ramp; vertical
    speed toward the goal's height; the avoider's side pushes. Subclasses say where the goal is."""

    name = "goal-seeker"

    def __init__(self, cfg: GoalSeekerConfig | None = None) -> None:
        self.cfg = cfg or GoalSeekerConfig()

    def reset(self, n: int, device: torch.device) -> None:
        return None

    @abstractmethod
    def goal(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(azimuth (N,) degrees in the body frame, left positive; elevation (N,) degrees; distance (N,) m)."""

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        cfg, avoid = self.cfg, self.cfg.avoid
        goal_az, goal_el, distance = self.goal(obs)  # (N,) each
        near = surroundings(obs, avoid)
        toward = 0.5 * (1.0 + torch.cos(torch.deg2rad(near.azimuth[None, :] - goal_az[:, None])))  # (N, Az)
        cap = (distance + 1.0).clamp(max=avoid.open_cap)[:, None]  # (N, 1)
        best = (torch.minimum(near.wide, cap) + cfg.goal_preference * toward).argmax(dim=1)  # (N,)
        error = near.azimuth[best]  # (N,) degrees
        yaw = (error / avoid.turn_angle).clamp(-1.0, 1.0)  # (N,)
        governor = ((near.wide[:, 0] - avoid.stop_distance) / avoid.brake_distance).clamp(0.0, 1.0)  # (N,)
        horizontal = distance * torch.cos(torch.deg2rad(goal_el))  # (N,) meters
        approach = (horizontal / cfg.approach_distance).clamp(0.1, 1.0)  # (N,)
        forward = governor * torch.cos(torch.deg2rad(error)).clamp(min=0.0) * approach  # (N,)
        climb = distance * torch.sin(torch.deg2rad(goal_el)) / cfg.climb_distance  # (N,)
        vertical = torch.where(
            near.vertical.abs() > 0.5, near.vertical, climb
        )  # (N,) the push wins near surfaces
        return torch.stack(
            [forward, vertical.clamp(-1.0, 1.0), near.lateral.clamp(-1.0, 1.0), yaw], dim=1
        )  # (N, 4)


class GreedyGoalPolicy(GoalSeekerPolicy):
    """Map-less point-goal baseline: straight at the goal as the observation's goal mark shows it (the
    mark's mean azimuth and elevation, its distance band), with the avoider."""

    name = "greedy"

    def goal(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        from navi_env.sim.goals import MARK_BANDS, MARK_EDGES

        avoid = self.cfg.avoid
        mark = obs[:, 1] < 0.0  # (N, Az, El) bool
        _, az, el = mark.shape
        dev = obs.device
        weight = mark.float()  # (N, Az, El)
        count = weight.sum(dim=(1, 2)).clamp(min=1.0)  # (N,)
        angle = torch.arange(az, device=dev) * (2.0 * math.pi / az)  # (Az,) radians, left positive
        per_az = weight.sum(dim=2)  # (N, Az)
        goal_az = torch.rad2deg(torch.atan2(per_az @ torch.sin(angle), per_az @ torch.cos(angle)))  # (N,)
        elevation = avoid.elevation_min + (torch.arange(el, device=dev) + 0.5) * (
            (avoid.elevation_max - avoid.elevation_min) / el
        )  # (El,) degrees
        goal_el = weight.sum(dim=1) @ elevation / count  # (N,)
        band = torch.round(-obs[:, 1].float().amin(dim=(1, 2)) * MARK_BANDS).long() - 1  # (N,)
        # each band read as its lower edge (0 for the first): short, so the drone slows down in time
        lower = torch.tensor((0.0, *MARK_EDGES), device=dev)  # (B,)
        distance = lower[band.clamp(0, MARK_BANDS - 1)]  # (N,)
        return goal_az, goal_el, distance


class OracleGoalPolicy(GoalSeekerPolicy):
    """Point-goal baseline with the map, the ceiling: along the true shortest path, read from the env's
    path-length field (the step of `probe` meters among 26 directions that lowers the path length most;
    straight at the goal within `straight` meters of it), with the avoider."""

    name = "oracle"

    def __init__(
        self, env: Any, cfg: GoalSeekerConfig | None = None, probe: float = 0.5, straight: float = 1.5
    ):
        super().__init__(cfg)
        if not capabilities(env).goal_paths:
            raise ValueError("the oracle needs a point-goal SdfDagEnv (EnvConfig(task='pointgoal'))")
        self.env, self.probe, self.straight = env, probe, straight
        offsets = torch.tensor(
            [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)],
            dtype=torch.float32,
        )  # (26, 3)
        self.directions = (offsets / offsets.norm(dim=1, keepdim=True)).to(env.device)  # (26, 3) unit

    def goal(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        from navi_env.sim.goals import goal_distance

        env = self.env
        n = env.n_actors
        probes = env.position[:, None, :] + self.probe * self.directions[None]  # (N, 26, 3)
        repeat = self.directions.shape[0]
        ahead = goal_distance(
            env.goal_bank,
            env.goal.repeat_interleave(repeat),
            env.scene.repeat_interleave(repeat),
            probes.reshape(-1, 3),
        ).reshape(n, repeat)  # (N, 26)
        downhill = self.directions[ahead.argmin(dim=1)]  # (N, 3) world unit direction
        offset = env.goal_position - env.position  # (N, 3)
        near = (env.goal_distance < self.straight)[:, None]  # (N, 1)
        heading = torch.where(near, offset, downhill)  # (N, 3)
        world_az = torch.atan2(heading[:, 1], heading[:, 0])  # (N,)
        goal_az = torch.rad2deg(
            torch.remainder(world_az - env.yaw + math.pi, 2.0 * math.pi) - math.pi
        )  # (N,)
        goal_el = torch.rad2deg(torch.atan2(heading[:, 2], heading[:, :2].norm(dim=1)))  # (N,)
        return goal_az, goal_el, env.goal_distance.clone()


def goal_seeker_for_env(name: str, env: Any) -> GoalSeekerPolicy:
    """The `greedy` or `oracle` point-goal baseline tuned to a point-goal drone env (its horizon and ray
    pattern); ValueError for any other env."""
    caps = capabilities(env)
    if caps.task != "pointgoal" or caps.horizon is None or caps.elevation_deg is None:
        raise ValueError("the point-goal baselines need a point-goal drone env (--task pointgoal)")
    low, high = caps.elevation_deg
    avoid = ReactiveConfig(horizon=caps.horizon, elevation_min=low, elevation_max=high)
    seeker = GoalSeekerConfig(avoid=avoid)
    return OracleGoalPolicy(env, seeker) if name == "oracle" else GreedyGoalPolicy(seeker)
