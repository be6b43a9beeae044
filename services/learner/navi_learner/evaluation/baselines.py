"""The baselines every trained drone is compared with: `random` and the scripted `reactive` avoider.

Both act on the same observation as the trained policy (channel 0 of the DistanceMatrix, depth /
horizon, azimuth bin 0 straight ahead and increasing to the left, elevation from bottom to top) and
are deterministic for a given seed. docs/TRAINING.md describes the reactive algorithm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
import torch.nn.functional as F

from navi_learner.engine.heads import ACTION_DIM


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
        wide = -F.max_pool1d(F.pad(-free[:, None], (k, k), mode="circular"), 2 * k + 1, stride=1)[
            :, 0
        ]  # (N, Az)
        ahead_bonus = cfg.ahead_preference * 0.5 * (1.0 + torch.cos(torch.deg2rad(azimuth)))  # (Az,)
        best = (wide.clamp(max=cfg.open_cap) + ahead_bonus).argmax(dim=1)  # (N,)
        error = azimuth[best]  # (N,) degrees, left positive
        yaw = (error / cfg.turn_angle).clamp(-1.0, 1.0)  # (N,)
        governor = ((wide[:, 0] - cfg.stop_distance) / cfg.brake_distance).clamp(0.0, 1.0)  # (N,)
        forward = governor * torch.cos(torch.deg2rad(error)).clamp(min=0.0)  # (N,)

        def side(lo: float, hi: float) -> torch.Tensor:
            mask = (azimuth >= lo) & (azimuth <= hi)  # (Az,) bool
            return wide[:, mask].amin(dim=1).clamp(max=cfg.side_distance)  # (N,)

        lateral = (side(60.0, 120.0) - side(-120.0, -60.0)) / cfg.side_distance  # (N,) + pushes left

        def cone(mask: torch.Tensor) -> torch.Tensor:
            if not bool(mask.any()):
                return torch.full((n,), cfg.side_distance, device=dev)
            return depth[:, :, mask].amin(dim=(1, 2)).clamp(max=cfg.side_distance)  # (N,)

        vertical = (cone(elevation >= 40.0) - cone(elevation <= -40.0)) / cfg.side_distance  # (N,) + climbs
        return torch.stack(
            [forward, vertical.clamp(-1.0, 1.0), lateral.clamp(-1.0, 1.0), yaw], dim=1
        )  # (N, 4)


def reactive_for(horizon: float, elevation_min: float, elevation_max: float) -> ReactivePolicy:
    """The reactive baseline for an environment's horizon and ray pattern."""
    return ReactivePolicy(
        ReactiveConfig(horizon=horizon, elevation_min=elevation_min, elevation_max=elevation_max)
    )


def reactive_for_env(env: object) -> ReactivePolicy:
    """The reactive baseline tuned to an env: the drone env's horizon and ray pattern (`config`), a
    toy env's `horizon`, or the defaults."""
    cfg = getattr(env, "config", None)
    if cfg is not None and hasattr(cfg, "sensor"):
        return reactive_for(cfg.horizon, cfg.sensor.elevation_min_deg, cfg.sensor.elevation_max_deg)
    horizon = getattr(env, "horizon", None)
    if isinstance(horizon, (int, float)):
        return reactive_for(float(horizon), -90.0, 90.0)
    return ReactivePolicy()
