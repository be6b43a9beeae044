"""The batched-environment protocol the learner trains against (implemented by navi_env.sim.env.SdfDagEnv
and by navi_learner.envs.toy.ToyEnv).

Layout of an observation (N, 3, Az, El) float32 (DistanceMatrix v2):
  channel 0  depth normalised by the horizon, in [0, 1] (1 = nothing within the horizon)
  channel 1  semantic (hit/miss or surface class)
  channel 2  delta depth since the previous step (0 after a reset)
  azimuth bin a is at angle 2π·a/Az in the body-yaw frame, bin 0 straight ahead, increasing to the left
  (counter-clockwise seen from above, the direction of a positive yaw rate);
  elevation bin e spans bottom (e = 0) to top (e = El-1).
Actions (N, 4) float32 in [-1, 1]: [forward, vertical, lateral, yaw_rate], body frame; the env scales
and clips them. Auto-reset: where done | truncated, the returned obs is already the first observation
of the actor's next episode (so the learner resets its recurrent state and episodic memory there).

Optional `info` keys the evaluator reads when present: "clearance" (N,) float32 metres,
"collision" (N,) bool, "position" (N, 3) float32 metres, "starved" (N,) bool (truncated for
starvation), "novel_cell" (N,) bool.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import torch


@dataclass
class StepOut:
    """What one batched step returns; every tensor lives on the env's device."""

    obs: torch.Tensor
    """(N, 3, Az, El) float32; the next episode's first observation where done | truncated."""
    reward: torch.Tensor
    """(N,) float32 extrinsic reward (sum of the weighted terms)."""
    done: torch.Tensor
    """(N,) bool terminated (the drone env never kills a drone; kept for generality)."""
    truncated: torch.Tensor
    """(N,) bool time limit or starvation; these actors were auto-reset."""
    reward_terms: dict[str, torch.Tensor] = field(default_factory=dict)
    """Per-term rewards, name -> (N,) float32, for metrics."""
    info: dict[str, torch.Tensor] = field(default_factory=dict)
    """Extra per-actor diagnostics (see the module docstring)."""


class StepLike(Protocol):
    """Read-only view of a step result: StepOut here, or any env's own dataclass with these fields."""

    @property
    def obs(self) -> torch.Tensor: ...
    @property
    def reward(self) -> torch.Tensor: ...
    @property
    def done(self) -> torch.Tensor: ...
    @property
    def truncated(self) -> torch.Tensor: ...
    @property
    def reward_terms(self) -> dict[str, torch.Tensor]: ...
    @property
    def info(self) -> dict[str, torch.Tensor]: ...


class BatchedEnv(Protocol):
    """N actors stepped together on one device.

    What an env may offer beyond these members is its capabilities (EnvCapabilities, read by
    `capabilities`): the learner and the baselines ask that one function, never the env itself.
    """

    @property
    def n_actors(self) -> int: ...
    @property
    def device(self) -> torch.device: ...
    @property
    def obs_shape(self) -> tuple[int, int, int]:
        """(3, Az, El)."""
        ...

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every actor; returns obs (N, 3, Az, El) float32."""
        ...

    def step(self, actions: torch.Tensor) -> StepLike:
        """Apply actions (N, 4) float32 in [-1, 1] and advance one step. The returned tensors may be the
        env's own buffers, valid until the next step: the learner copies what it keeps."""
        ...


@dataclass(frozen=True)
class EnvCapabilities:
    """What an env offers beyond BatchedEnv, each optional; the defaults are those of an env that offers
    none (the toy env offers `horizon`, the drone env navi_env.sim.env.SdfDagEnv all of them)."""

    compact_obs: bool = False
    """Observations are DistanceMatrix v2 exactly as navi_env.sim.observation writes them (channel 0
    float16 values, channel 1 from the semantic table, channel 2 the difference of consecutive channel
    0s, 0 where an episode starts): rollouts are then stored in 3 bytes per ray (navi_learner.ppo.rollout),
    else as float32. The env's `compact_obs` attribute."""
    goal_marks: bool = False
    """Channel 1 carries point-goal marks (semantic codes of the goal bands). The env's `goal_marks`."""
    goal_paths: bool = False
    """The env holds path lengths to its goals (a point-goal drone env's `goal_bank`), which the oracle
    baseline follows."""
    task: str = "explore"
    """The episodes' task: "explore" or "pointgoal" (the drone env's config.task)."""
    shaping_gamma: float | None = None
    """The discount of the env's potential-based reward shaping (config.reward.shaping_gamma)."""
    horizon: float | None = None
    """Meters that depth 1.0 in channel 0 stands for (config.horizon, or the env's own `horizon`)."""
    elevation_deg: tuple[float, float] | None = None
    """The rays' lowest and highest elevation in degrees (config.sensor); None where not known."""
    dt: float = 0.1
    """Seconds per step (config.dt)."""
    scenes: tuple[str, ...] = ()
    """Names of the scenes the env flies (its corpus's infos)."""


def capabilities(env: Any) -> EnvCapabilities:
    """The capabilities `env` declares: its `compact_obs`, `goal_marks`, `goal_bank`, `horizon` and
    `corpus` attributes, and its `config` (a navi_env EnvConfig: task, reward.shaping_gamma, horizon,
    sensor, dt) where it has one; the EnvCapabilities default for each one it lacks."""
    cfg: Any = getattr(env, "config", None)
    sensor = getattr(cfg, "sensor", None)
    horizon = getattr(env, "horizon", None)
    if sensor is not None:
        horizon, elevation = float(cfg.horizon), (sensor.elevation_min_deg, sensor.elevation_max_deg)
    else:
        horizon, elevation = (float(horizon) if isinstance(horizon, (int, float)) else None), None
    shaping_gamma = getattr(getattr(cfg, "reward", None), "shaping_gamma", None)
    infos = getattr(getattr(env, "corpus", None), "infos", None) or []
    return EnvCapabilities(
        compact_obs=bool(getattr(env, "compact_obs", False)),
        goal_marks=bool(getattr(env, "goal_marks", False)),
        goal_paths=getattr(env, "goal_bank", None) is not None,
        task=str(getattr(cfg, "task", "explore")),
        shaping_gamma=None if shaping_gamma is None else float(shaping_gamma),
        horizon=horizon,
        elevation_deg=elevation,
        dt=float(getattr(cfg, "dt", 0.1)),
        scenes=tuple(str(getattr(info, "name", "")) for info in infos),
    )
