"""Gymnasium 1.x over the batched env: `gymnasium.make_vec("Navi/Explore-v0", num_envs=N, corpus=DIR,
device="cuda")` gives a NaviVectorEnv whose observations, rewards, terminations, truncations and info
are torch tensors on the env's device (the convention of Isaac Lab and ManiSkill3); `numpy=True` gives
NumpyVectorEnv (host NumPy arrays, for CPU libraries); `gymnasium.make("Navi/Explore-v0", corpus=DIR)`
gives NaviEnv, one drone with NumPy arrays (what `gymnasium.utils.env_checker.check_env` checks).

Autoreset is SAME_STEP: SdfDagEnv starts the next episode of an actor inside the step that ended its
episode, so the observation returned for that actor is the first of its next episode, and
info["final_obs"] (where info["_final_obs"]) holds its final observation. The env does not trace an
ended actor at its final pose: its final observation is its last view, the one its last action was
chosen on (the reward uses the same view as s'). docs/ENVIRONMENT.md describes spaces, info and modes.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, overload

import gymnasium
import numpy as np
import torch
from gymnasium.spaces import Box
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import ACTION_DIM, make_batched_env, obs_bounds, pointgoal_config
from navi_env.ecosystem.render import render_frame
from navi_env.sim.env import SdfDagEnv

ENV_ID = "Navi/Explore-v0"
"""The Gymnasium id: fly a corpus's scenes, rewarded by docs/SIMULATION.md's terms."""
POINTGOAL_ID = "Navi/PointGoal-v0"
"""The Gymnasium id of point-goal episodes: fly to a goal in a corpus's scenes (docs/TASKS.md)."""
RENDER_FPS = 10
"""One step is 0.1 s of simulated time."""


def spaces_of(env: SdfDagEnv) -> tuple[Box, Box]:
    """(observation, action) space of one drone: (3, Az, El) float32 within its channel bounds, and
    (4,) float32 in [-1, 1]."""
    low, high = obs_bounds(env)  # (3, Az, El) each
    observation = Box(low.numpy(), high.numpy(), dtype=np.float32)
    action = Box(-1.0, 1.0, (ACTION_DIM,), dtype=np.float32)
    return observation, action


class ActorFrames(Sequence[np.ndarray]):
    """The vector env's pictures, one per actor, each drawn when it is read (`frames[i]`, (H, W, 3)
    uint8): Gymnasium's vector render returns a sequence of num_envs frames, and a video of the first
    actor (RecordVideo(record_first_only=True)) then costs one picture per step."""

    def __init__(self, env: SdfDagEnv) -> None:
        self.env = env

    def __len__(self) -> int:
        return self.env.n_actors

    @overload
    def __getitem__(self, index: int) -> np.ndarray: ...
    @overload
    def __getitem__(self, index: slice) -> Sequence[np.ndarray]: ...
    def __getitem__(self, index: int | slice) -> np.ndarray | Sequence[np.ndarray]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if not -len(self) <= index < len(self):
            raise IndexError(f"actor {index} out of range for {len(self)} actors")
        return render_frame(self.env, self.env.obs, index % len(self))


class NaviVectorEnv(VectorEnv[torch.Tensor, torch.Tensor, torch.Tensor]):
    """N drones of one SdfDagEnv as a Gymnasium vector env, tensors on the env's device.

    step(actions (N, 4)) -> obs (N, 3, Az, El) float32, reward (N,) float32, terminated (N,) bool
    (at the goal in point-goal episodes; never when exploring: contact never ends an episode),
    truncated (N,) bool, info. Reward, terminated,
    truncated and info's tensors are the env's own buffers, overwritten by the next step.

    The observation is the env's own buffer, never copied. With final_obs (the default) the env writes
    its two observation buffers in turn (EnvConfig.obs_buffers=2, as make_batched_env builds it): the
    observation handed out stays intact through the next step (skrl records it after stepping) and
    info["final_obs"] is the previous one (SdfDagEnv.previous_obs), the final view of the actors that
    ended. With final_obs=False info has no final_obs and one buffer will do: for loops that store the
    observation before they step. No step copies the observation, allocates device memory or waits for
    the device.

    info: every key of SdfDagEnv's StepOut.info ((N,) or (N, 3) tensors of the step that just ended:
    clearance, collision, position, novel_cell, speed, episode_return, episode_length, starved, scene_id,
    obstacle_collision, drone_collision; point-goal episodes add success, goal_distance, start_distance
    and path_length), "reward_terms" (term name -> (N,) weighted term; they sum to
    the reward), "final_obs" / "_final_obs" and "final_info" / "_final_info" (the same per-actor values,
    which already describe the step that ended) with the mask of the actors whose episode ended.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012 (Gymnasium reads it from the class)
        "autoreset_mode": AutoresetMode.SAME_STEP,
        "render_modes": ["rgb_array"],
        "render_fps": RENDER_FPS,
        "torch": True,
    }

    def __init__(self, env: SdfDagEnv, final_obs: bool = True, render_mode: str | None = None) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.env = env
        self.num_envs = env.n_actors
        self.device = env.device
        self.render_mode = render_mode
        self.single_observation_space, self.single_action_space = spaces_of(env)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        if final_obs and env.config.obs_buffers < 2:
            raise ValueError(
                "final_obs needs an env that keeps its previous observation: EnvConfig(obs_buffers=2), as "
                "make_batched_env builds it (or final_obs=False)"
            )
        self.final_obs = final_obs
        self.ended = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)  # (N,) done | truncated
        self._info: dict[str, Any] = {
            **env.info,
            "reward_terms": env.terms,
            "final_info": dict(env.info),
            "_final_info": self.ended,
        }
        if final_obs:
            self._info |= {"_final_obs": self.ended}

    def actions(self, actions: torch.Tensor | np.ndarray) -> torch.Tensor:
        """(N, 4) float32 on the env's device: a tensor already there passes as it is."""
        return torch.as_tensor(actions, dtype=torch.float32, device=self.device)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[torch.Tensor, dict[str, Any]]:
        """Start every actor's first episode. `seed` seeds the env (the same seed gives the same episodes
        bit for bit on the CPU); without it the seed is drawn from the generator a previous seed set."""
        super().reset(seed=seed)
        if options:
            raise ValueError(f"NaviVectorEnv.reset takes no options, got {sorted(options)}")
        env_seed = seed if seed is not None else int(self.np_random.integers(2**31))
        obs = self.env.reset(seed=env_seed)  # (N, 3, Az, El)
        self.ended.zero_()
        return obs, {}

    def step(
        self, actions: torch.Tensor | np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        out = self.env.step(self.actions(actions))
        torch.logical_or(out.done, out.truncated, out=self.ended)
        obs = out.obs  # (N, 3, Az, El)
        info = dict(self._info)
        if self.final_obs:
            info["final_obs"] = self.env.previous_obs  # (N, 3, Az, El) the view the actions were chosen on
        return obs, out.reward, out.done, out.truncated, info

    def render(self) -> ActorFrames | None:  # type: ignore[override]
        """One picture per actor ((H, W, 3) uint8, drawn when read): its view as a panorama above a
        top-down slice of its scene (navi_env.ecosystem.render); None without render_mode."""
        return ActorFrames(self.env) if self.render_mode == "rgb_array" else None


def to_numpy(value: Any) -> Any:
    """Host NumPy copies of every tensor in value (dicts recursively)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy().copy()
    if isinstance(value, dict):
        return {k: to_numpy(v) for k, v in value.items()}
    return value


class NumpyVectorEnv(VectorWrapper):
    """A NaviVectorEnv with NumPy arrays in and out (fresh host copies at every step), for libraries
    that work on the host. Each step reads the device once."""

    def __init__(self, env: NaviVectorEnv) -> None:
        super().__init__(env)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        return to_numpy(obs), to_numpy(info)

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(actions)
        return to_numpy(obs), to_numpy(reward), to_numpy(terminated), to_numpy(truncated), to_numpy(info)


def make_vector_env(
    num_envs: int,
    corpus: str | os.PathLike[str],
    device: str = "cpu",
    config: EnvConfig | None = None,
    obstacles: int = 0,
    squad: int = 0,
    max_episode_steps: int = 0,
    final_obs: bool = True,
    numpy: bool = False,
    render_mode: str | None = None,
) -> NaviVectorEnv | NumpyVectorEnv:
    """The vector entry point of Navi/Explore-v0 (arguments of navi_env.ecosystem.batch.make_batched_env,
    then NaviVectorEnv's; numpy=True wraps it in NumpyVectorEnv)."""
    batched = make_batched_env(corpus, num_envs, device, config, obstacles, squad, max_episode_steps)
    env = NaviVectorEnv(batched, final_obs=final_obs, render_mode=render_mode)
    return NumpyVectorEnv(env) if numpy else env


class NaviEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """One drone as a Gymnasium Env with NumPy arrays (a view of a one-actor NaviVectorEnv): for
    `gymnasium.make`, `check_env` and single-env libraries. Training wants the vector env.

    When an episode ends, step returns its final observation with truncated=True, as a single Env does;
    the env has already started the next episode, and the next reset() without a seed returns its first
    observation. reset(seed=...) restarts the drone from that seed."""

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}  # noqa: RUF012

    def __init__(
        self,
        corpus: str | os.PathLike[str],
        device: str = "cpu",
        config: EnvConfig | None = None,
        obstacles: int = 0,
        max_episode_steps: int = 0,
        render_mode: str | None = None,
    ) -> None:
        batched = make_batched_env(corpus, 1, device, config, obstacles, 0, max_episode_steps)
        self.vector = NaviVectorEnv(batched, final_obs=True, render_mode=render_mode)
        self.render_mode = render_mode
        self.observation_space = self.vector.single_observation_space
        self.action_space = self.vector.single_action_space
        self._started = False  # the env began the drone's next episode at the last step

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if seed is None and self._started:
            obs = self.vector.env.obs  # (1, 3, Az, El): the episode the env started at the last step
        else:
            env_seed = seed if seed is not None else int(self.np_random.integers(2**31))
            obs, _ = self.vector.reset(seed=env_seed, options=options)
        self._started = False
        return to_numpy(obs[0]), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.vector.step(np.asarray(action, np.float32)[None])
        ended = bool(self.vector.ended[0])
        if ended:
            obs = info["final_obs"]  # (1, 3, Az, El) the last view of the episode that ended
        self._started = ended
        values = {k: to_numpy(v[0]) for k, v in self.vector.env.info.items()}
        values["reward_terms"] = {k: float(v[0]) for k, v in self.vector.env.terms.items()}
        return to_numpy(obs[0]), float(reward[0]), bool(terminated[0]), bool(truncated[0]), values

    def render(self) -> np.ndarray | None:
        frames = self.vector.render()
        return frames[0] if frames is not None else None


def make_pointgoal_vector_env(
    num_envs: int, corpus: str | os.PathLike[str], config: EnvConfig | None = None, **kwargs: Any
) -> NaviVectorEnv | NumpyVectorEnv:
    """The vector entry point of Navi/PointGoal-v0: make_vector_env with `config` made point-goal
    (navi_env.ecosystem.batch.pointgoal_config); the other arguments are make_vector_env's."""
    return make_vector_env(num_envs, corpus, config=pointgoal_config(config), **kwargs)


class PointGoalEnv(NaviEnv):
    """One drone flying point-goal episodes (NaviEnv with `config` made point-goal): terminated is True
    on the step that reaches the goal."""

    def __init__(
        self, corpus: str | os.PathLike[str], config: EnvConfig | None = None, **kwargs: Any
    ) -> None:
        super().__init__(corpus, config=pointgoal_config(config), **kwargs)


def register_envs() -> None:
    """Register Navi/Explore-v0 and Navi/PointGoal-v0 with Gymnasium (NaviEnv or PointGoalEnv for make,
    make_vector_env or make_pointgoal_vector_env for make_vec)."""
    entries = (
        (ENV_ID, "NaviEnv", "make_vector_env"),
        (POINTGOAL_ID, "PointGoalEnv", "make_pointgoal_vector_env"),
    )
    for env_id, single, vector in entries:
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point=f"navi_env.ecosystem.gym:{single}",
                vector_entry_point=f"navi_env.ecosystem.gym:{vector}",
            )
