"""skrl over the batched env: SkrlEnv is skrl's torch Wrapper interface over a NaviVectorEnv, so skrl's
agents and trainers run on Navi's tensors where they live (no NumPy round trip, no host sync).

skrl flattens observations: step and reset return obs (N, 3·Az·El) (a view of the vector env's
observation, which the env keeps intact through the next step, as skrl's trainer records it after
stepping), reward (N, 1), terminated (N, 1), truncated (N, 1) and the vector env's info. Autoreset is
the vector env's SAME_STEP: skrl never resets a vectorised env after the first reset.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import torch
from skrl.envs.wrappers.torch import Wrapper

from navi_env.ecosystem.gym import NaviVectorEnv


class SkrlEnv(Wrapper):
    """A NaviVectorEnv (final_obs=True: each observation intact through the next step) as a skrl
    environment."""

    def __init__(self, env: NaviVectorEnv, seed: int = 0) -> None:
        if not env.final_obs:
            raise ValueError(
                "SkrlEnv needs observations that stay intact through the next step (NaviVectorEnv(final_obs=True))"
            )
        super().__init__(env)
        self.vector = env
        self.seed = seed
        self.obs: torch.Tensor | None = None  # (N, 3·Az·El) the latest observation
        self.info: dict[str, Any] = {}

    @property
    def observation_space(self) -> gymnasium.Space[Any]:
        """One drone's observation, (3, Az, El)."""
        return self.vector.single_observation_space

    @property
    def action_space(self) -> gymnasium.Space[Any]:
        """One drone's action, (4,) in [-1, 1]."""
        return self.vector.single_action_space

    @property
    def num_envs(self) -> int:
        return self.vector.num_envs

    def reset(self) -> tuple[torch.Tensor, dict[str, Any]]:
        """The first call resets the vector env with the seed; later calls return the latest observation
        (the vector env resets its actors itself)."""
        if self.obs is None:
            obs, self.info = self.vector.reset(seed=self.seed)
            self.obs = obs.view(self.vector.num_envs, -1)  # (N, 3·Az·El)
        return self.obs, self.info

    def step(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, Any]:
        obs, reward, terminated, truncated, self.info = self.vector.step(actions)
        self.obs = obs.view(self.vector.num_envs, -1)  # (N, 3·Az·El)
        return self.obs, reward[:, None], terminated[:, None], truncated[:, None], self.info

    def state(self) -> torch.Tensor | None:
        """No separate critic state: skrl's agents read the observation."""
        return None

    def render(self, *args: Any, **kwargs: Any) -> Any:
        return self.vector.render()

    def close(self) -> None:
        self.vector.close()
