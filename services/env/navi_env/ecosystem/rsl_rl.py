"""rsl_rl over the batched env: RslRlEnv is rsl_rl's VecEnv (rsl-rl-lib 5.5) over a NaviVectorEnv, so
rsl_rl's OnPolicyRunner trains on Navi's tensors where they live (no host sync per step).

Observations are a TensorDict of batch size (N,) with two observation groups, "policy" and "critic",
both the flat view an MLP reads: (N, 3·Az'·El'), the pooled view of navi_env.ecosystem.batch.pool_view
(MLP_VIEW = 16 x 4 by default), or with view=None (or an env already at that view) a view of the vector
env's observation (N, 3·Az·El). The runner's `obs_groups` maps them: {"actor": ["policy"], "critic":
["critic"]} (OBS_GROUPS). step(actions (N, 4)) returns (obs, rewards (N,) float32, dones (N,) int64,
extras): dones marks every episode that ended (terminated at the goal in point-goal episodes, or
truncated), extras["time_outs"] (N,) bool the truncated ones (time limit, starvation), which rsl_rl's
PPO bootstraps from the value, and extras["log"] Navi's metrics of the step averaged over the actors
("Navi/..." scalars on the device: collisions and novel cells per 1,000 steps, clearance, speed, each
reward term), which rsl_rl's logger averages over an iteration.

episode_length_buf is the env's own step counter (N,) int64: the runner's init_at_random_ep_len writes
random lengths into it, so the time limits of the actors are spread over an episode instead of all
falling on the same step.
"""

from __future__ import annotations

from typing import Any

import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from navi_env.ecosystem.batch import ACTION_DIM, MLP_VIEW, pool_view, view_of
from navi_env.ecosystem.gym import NaviVectorEnv

OBS_GROUPS: dict[str, list[str]] = {"actor": ["policy"], "critic": ["critic"]}
"""The runner configuration's `obs_groups` for RslRlEnv's observation groups."""


class RslRlEnv(VecEnv):
    """A NaviVectorEnv (final_obs=True: each observation intact through the next step) as an rsl_rl VecEnv
    whose observation groups hold the pooled view `view` (None: the env's own view)."""

    def __init__(self, env: NaviVectorEnv, seed: int = 0, view: tuple[int, int] | None = MLP_VIEW) -> None:
        if not env.final_obs:
            raise ValueError(
                "RslRlEnv needs observations that stay intact through the next step (NaviVectorEnv(final_obs=True))"
            )
        self.vector = env
        self.num_envs = env.num_envs
        self.num_actions = ACTION_DIM
        self.device = env.device
        self.cfg = env.env.config
        self.max_episode_length = env.env.config.max_steps_per_episode
        self.view = view_of(env.env, view)
        self.seed = seed
        self.obs = self.observations(env.reset(seed=seed)[0])

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Steps of every actor's running episode, (N,) int64: the env's own counter."""
        return self.vector.env.steps

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.vector.env.steps.copy_(value)

    def observations(self, obs: torch.Tensor) -> TensorDict:
        """The observation groups of the env's obs (N, 3, Az, El): "policy" and "critic", (N, 3·Az'·El')."""
        seen = obs if self.view is None else pool_view(obs, self.view)  # (N, 3, Az', El')
        flat = seen.reshape(seen.shape[0], -1)  # (N, 3·Az'·El')
        return TensorDict({"policy": flat, "critic": flat}, batch_size=[flat.shape[0]], device=flat.device)

    def get_observations(self) -> TensorDict:
        """The latest observation groups."""
        return self.obs

    def reset(self) -> tuple[TensorDict, dict[str, Any]]:
        """Restart every actor from the seed; returns (observation groups, {})."""
        self.obs = self.observations(self.vector.reset(seed=self.seed)[0])
        return self.obs, {}

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.vector.step(actions)
        self.obs = self.observations(obs)
        dones = (terminated | truncated).long()  # (N,) 1 where the episode ended (the env began the next)
        extras = {"time_outs": truncated, "log": metrics(info)}
        return self.obs, reward, dones, extras

    def close(self) -> None:
        self.vector.close()


def metrics(info: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Navi's per-step metrics averaged over the actors, 0-dim tensors on the env's device: collisions and
    novel cells per 1,000 steps, clearance (m), speed (m/s) and each reward term."""
    out = {
        "Navi/collisions_per_1k": info["collision"].float().mean() * 1000.0,  # ()
        "Navi/novel_cells_per_1k": info["novel_cell"].float().mean() * 1000.0,  # ()
        "Navi/clearance_m": info["clearance"].mean(),  # ()
        "Navi/speed_m_s": info["speed"].mean(),  # ()
    }
    for term, value in info["reward_terms"].items():
        out[f"Navi/reward_{term}"] = value.mean()  # ()
    return out
