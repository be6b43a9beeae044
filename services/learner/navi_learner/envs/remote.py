"""A BatchedEnv over Zenoh: drives a `navi serve env` through its step queryable (`navi infer --remote`).

Every step is one StepRequest → StepResult round trip carrying the actions of all N actors and
their next DistanceMatrix. zenoh and the contracts are imported when a RemoteEnv is built, so this
module imports with torch and numpy alone.
"""

from __future__ import annotations

import itertools
import os
from typing import Any

import numpy as np
import torch

from navi_learner.envs.protocol import StepOut


class RemoteEnvError(RuntimeError):
    """The env service did not answer, or answered with an error."""


class RemoteEnv:
    """The first `n_actors` drones of a remote env service, as a BatchedEnv on `device`."""

    def __init__(
        self, n_actors: int, device: torch.device | str = "cpu", timeout_s: float = 30.0, sess: Any = None
    ) -> None:
        from navi_contracts.settings import NaviSettings
        from navi_mesh.session import config_from_settings, session

        if n_actors < 1:
            raise ValueError("n_actors must be >= 1")
        self.n_actors = n_actors
        self.device = torch.device(device)
        self.timeout_s = timeout_s
        self.sess = sess if sess is not None else session(config_from_settings(NaviSettings()))
        self.env_ids = np.arange(n_actors, dtype=np.int32)  # (N,) int32
        self._ids = itertools.count()
        self._prefix = f"infer-{os.getpid()}-"
        self.obs_shape: tuple[int, int, int] = (3, 0, 0)

    def _call(self, actions: np.ndarray, reset: bool) -> Any:
        from navi_contracts.models import StepRequest, StepResult
        from navi_contracts.topics import STEP
        from navi_mesh.pubsub import RequestError, request

        req = StepRequest(
            request_id=f"{self._prefix}{next(self._ids)}", env_ids=self.env_ids, actions=actions, reset=reset
        )
        try:
            result = request(self.sess, STEP.key, req, StepResult, self.timeout_s)
        except RequestError as exc:
            raise RemoteEnvError(f"env service: {exc}") from exc
        if result.observation is None:
            raise RemoteEnvError("env service answered without an observation")
        return result

    def _obs(self, result: Any) -> torch.Tensor:
        dm = result.observation
        obs = torch.stack(
            [torch.from_numpy(dm.depth.copy()), torch.from_numpy(dm.semantic.copy()),
             torch.from_numpy(dm.delta_depth.copy())], dim=1,
        )  # fmt: skip  # (N, 3, Az, El) float32
        self.obs_shape = (3, int(obs.shape[2]), int(obs.shape[3]))
        return obs.to(self.device)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset the remote env (all its drones) and return obs (N, 3, Az, El)."""
        result = self._call(np.zeros((self.n_actors, 4), np.float32), reset=True)  # (N, 4)
        return self._obs(result)

    def step(self, actions: torch.Tensor) -> StepOut:
        """One remote step with actions (N, 4) in [-1, 1]."""
        act = actions.detach().to("cpu", torch.float32).contiguous().numpy()  # (N, 4)
        result = self._call(act, reset=False)
        ret = torch.from_numpy(result.episode_return.copy())  # (N,) float32
        dev = self.device
        return StepOut(
            obs=self._obs(result),
            reward=torch.from_numpy(result.reward.copy()).to(dev),  # (N,) float32
            done=torch.from_numpy(result.done.copy()).to(dev),  # (N,) bool
            truncated=torch.from_numpy(result.truncated.copy()).to(dev),  # (N,) bool
            reward_terms={},
            info={"episode_return": ret.to(dev)},
        )
