"""ToyEnv: a tiny, fast, batched environment that implements BatchedEnv, for tests and benchmarks.

Each actor has a hidden target bearing. Channel 0 of the observation shows an open direction (large
depth) around that bearing in the body-yaw frame (azimuth bin 0 straight ahead, angles increasing to
the left, as in the drone env), channel 1 marks open bins and channel 2 is the change in depth.
Reward per step = forward · cos(bearing): fly forward when the target is ahead, turn (yaw) toward it.
A random policy earns 0 on average; a good one approaches 1 per step. Episodes truncate after
`max_steps` (auto-reset, staggered start counters).
"""

from __future__ import annotations

import math

import torch

from navi_learner.envs.protocol import StepOut

YAW_GAIN = 0.5
"""Radians turned per step at yaw_rate = 1."""
SPEED = 1.0
"""Metres flown per step at forward = 1."""


class ToyEnv:
    """BatchedEnv with obs (N, 3, Az, El); default Az×El = 16×8."""

    horizon = 10.0
    """Meters that depth 1.0 in channel 0 stands for (the reported clearance is 10 · depth ahead)."""

    def __init__(
        self,
        n_actors: int,
        device: torch.device | str = "cpu",
        az: int = 16,
        el: int = 8,
        max_steps: int = 64,
        seed: int = 0,
    ) -> None:
        self.n_actors = n_actors
        self.device = torch.device(device)
        self.obs_shape = (3, az, el)
        self.max_steps = max_steps
        self.gen = torch.Generator(device=self.device).manual_seed(seed)
        self.bin_angle = 2 * math.pi * torch.arange(az, device=self.device) / az  # (Az,) float32
        self.target = torch.zeros(n_actors, device=self.device)  # (N,) world bearing of the target
        self.heading = torch.zeros(n_actors, device=self.device)  # (N,) world heading
        self.position = torch.zeros(n_actors, 3, device=self.device)  # (N, 3) metres
        self.t = torch.zeros(n_actors, dtype=torch.long, device=self.device)  # (N,) steps in episode
        self.depth = torch.zeros(n_actors, az, device=self.device)  # (N, Az) last depth profile

    def _bearing(self) -> torch.Tensor:
        """Target bearing in the body frame, wrapped to (-π, π]; (N,)."""
        return torch.remainder(self.target - self.heading + math.pi, 2 * math.pi) - math.pi

    def _profile(self) -> torch.Tensor:
        """Depth per azimuth bin (N, Az): open (→1) around the target bearing, walls (0.15) elsewhere."""
        diff = (
            torch.remainder(self.bin_angle[None] - self._bearing()[:, None] + math.pi, 2 * math.pi) - math.pi
        )
        return 0.15 + 0.85 * torch.exp(-0.5 * (diff / 0.5).pow(2))  # (N, Az)

    def _respawn(self, mask: torch.Tensor) -> None:
        u = torch.rand(self.n_actors, generator=self.gen, device=self.device)  # (N,)
        self.target = torch.where(mask, 2 * math.pi * u, self.target)
        self.heading = torch.where(mask, torch.zeros_like(self.heading), self.heading)  # (N,)
        self.position = torch.where(mask[:, None], torch.zeros_like(self.position), self.position)  # (N, 3)
        self.t = torch.where(mask, torch.zeros_like(self.t), self.t)  # (N,) int64

    def _obs(self, fresh: torch.Tensor) -> torch.Tensor:
        depth = self._profile()  # (N, Az)
        delta = torch.where(fresh[:, None], torch.zeros_like(depth), depth - self.depth)  # (N, Az)
        self.depth = depth
        el = self.obs_shape[2]
        chans = torch.stack([depth, (depth > 0.5).float(), delta], dim=1)  # (N, 3, Az)
        return chans[..., None].expand(-1, -1, -1, el).contiguous()  # (N, 3, Az, El) float32

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """New episodes for every actor; start counters are staggered so truncations spread out."""
        if seed is not None:
            self.gen.manual_seed(seed)
        everyone = torch.ones(self.n_actors, dtype=torch.bool, device=self.device)  # (N,)
        self._respawn(everyone)
        self.t = torch.randint(0, self.max_steps, (self.n_actors,), generator=self.gen, device=self.device)
        return self._obs(everyone)

    def step(self, actions: torch.Tensor) -> StepOut:
        """actions (N, 4) in [-1, 1] (clipped here): forward and yaw_rate matter."""
        a = actions.clamp(-1.0, 1.0)  # (N, 4)
        forward, yaw = a[:, 0], a[:, 3]  # (N,) each
        bearing = self._bearing()  # (N,)
        progress = forward * torch.cos(bearing)  # (N,)
        front = self.depth[:, 0]  # (N,) depth straight ahead before moving
        collision = (front < 0.2) & (forward > 0.5)  # (N,) bool
        flat = torch.zeros_like(forward)  # (N,)
        step_vec = torch.stack([torch.cos(self.heading), torch.sin(self.heading), flat], 1)  # (N, 3)
        self.position = self.position + SPEED * forward.clamp(min=0.0)[:, None] * step_vec  # (N, 3)
        self.heading = self.heading + YAW_GAIN * yaw
        self.t = self.t + 1
        truncated = self.t >= self.max_steps  # (N,) bool
        info = {
            "clearance": self.horizon * front,
            "collision": collision,
            "position": self.position.clone(),
            "starved": torch.zeros_like(truncated),  # (N,) bool
        }
        self._respawn(truncated)
        obs = self._obs(truncated)
        done = torch.zeros_like(truncated)  # (N,) bool: the toy never terminates
        return StepOut(obs, progress, done, truncated, {"progress": progress}, info)
