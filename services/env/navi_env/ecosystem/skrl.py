"""skrl over the batched env: SkrlEnv is skrl's torch Wrapper interface over a NaviVectorEnv, so skrl's
agents and trainers run on Navi's tensors where they live (no NumPy round trip, no host sync).

skrl flattens observations: step and reset return obs (N, 3·Az'·El'), the pooled view an MLP reads
(navi_env.ecosystem.batch.pool_view, MLP_VIEW = 16 x 4 by default: a new tensor per step), or with
view=None (or an env already at that view) a view of the vector env's observation (N, 3·Az·El), which
the env keeps intact through the next step, as skrl's trainer records it after stepping. reward (N, 1),
terminated (N, 1) (only point-goal episodes terminate, at the goal), truncated (N, 1) (the time limit,
starvation) and the vector env's info. Autoreset is the vector env's SAME_STEP: skrl never resets a
vectorised env after the first reset.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium.spaces import Box
from skrl.envs.wrappers.torch import Wrapper

from navi_env.ecosystem.batch import MLP_VIEW, obs_bounds, pool_view, view_of
from navi_env.ecosystem.gym import NaviVectorEnv


class SkrlEnv(Wrapper):
    """A NaviVectorEnv (final_obs=True: each observation intact through the next step) as a skrl
    environment whose observations are the pooled view `view` (None: the env's own view)."""

    def __init__(self, env: NaviVectorEnv, seed: int = 0, view: tuple[int, int] | None = MLP_VIEW) -> None:
        if not env.final_obs:
            raise ValueError(
                "SkrlEnv needs observations that stay intact through the next step (NaviVectorEnv(final_obs=True))"
            )
        super().__init__(env)
        self.vector = env
        self.seed = seed
        self.view = view_of(env.env, view)
        low, high = obs_bounds(env.env, self.view)  # (3, Az', El') each
        self._observation_space = Box(low.numpy(), high.numpy(), dtype=np.float32)
        self.obs: torch.Tensor | None = None  # (N, 3·Az'·El') the latest observation
        self.info: dict[str, Any] = {}

    @property
    def observation_space(self) -> gymnasium.Space[Any]:
        """One drone's observation, (3, Az', El')."""
        return self._observation_space

    @property
    def action_space(self) -> gymnasium.Space[Any]:
        """One drone's action, (4,) in [-1, 1]."""
        return self.vector.single_action_space

    @property
    def num_envs(self) -> int:
        return self.vector.num_envs

    def flat(self, obs: torch.Tensor) -> torch.Tensor:
        """obs (N, 3, Az, El) as skrl reads it: (N, 3·Az'·El'), pooled where the adapter pools."""
        seen = obs if self.view is None else pool_view(obs, self.view)  # (N, 3, Az', El')
        return seen.reshape(seen.shape[0], -1)  # (N, 3·Az'·El')

    def reset(self) -> tuple[torch.Tensor, dict[str, Any]]:
        """The first call resets the vector env with the seed; later calls return the latest observation
        (the vector env resets its actors itself)."""
        if self.obs is None:
            obs, self.info = self.vector.reset(seed=self.seed)
            self.obs = self.flat(obs)  # (N, 3·Az'·El')
        return self.obs, self.info

    def step(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, Any]:
        obs, reward, terminated, truncated, self.info = self.vector.step(actions)
        self.obs = self.flat(obs)  # (N, 3·Az'·El')
        return self.obs, reward[:, None], terminated[:, None], truncated[:, None], self.info

    def state(self) -> torch.Tensor | None:
        """No separate critic state: skrl's agents read the observation."""
        return None

    def render(self, *args: Any, **kwargs: Any) -> Any:
        return self.vector.render()

    def close(self) -> None:
        self.vector.close()
