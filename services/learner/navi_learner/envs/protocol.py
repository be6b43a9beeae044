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
from typing import Protocol

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

    An env whose observations are DistanceMatrix v2 exactly as navi_env.sim.observation writes them (channel
    0 float16 values, channel 1 from the semantic table, channel 2 the difference of consecutive channel
    0s, 0 where an episode starts) says so with a true `compact_obs` attribute: its rollouts are then
    stored in 3 bytes per ray (navi_learner.ppo.rollout). Without it, or false, they are stored as float32.
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
