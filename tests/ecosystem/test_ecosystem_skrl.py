"""The skrl adapter hands skrl flat views of the vector env's tensors: observations (N, 3·Az·El) that
stay intact while skrl records them after the next step, (N, 1) rewards and flags, single spaces."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from navi_env.ecosystem.batch import make_batched_env
from navi_env.ecosystem.gym import NaviVectorEnv, make_vector_env
from navi_env.ecosystem.skrl import SkrlEnv

from .conftest import SMALL_VIEW

pytestmark = pytest.mark.usefixtures("single_thread")
N = 8


def test_skrl_env_hands_out_flat_views_that_survive_the_next_step(corpus: Path) -> None:
    vector = make_vector_env(N, corpus, config=SMALL_VIEW)
    assert isinstance(vector, NaviVectorEnv)
    env = SkrlEnv(vector, seed=3)
    raw = make_batched_env(corpus, N, "cpu", SMALL_VIEW)
    assert env.num_envs == N and env.observation_space.shape == (3, 16, 4) and env.action_space.shape == (4,)
    obs, _ = env.reset()
    assert torch.equal(obs, raw.reset(seed=3).reshape(N, -1)) and env.reset()[0] is obs  # reset once
    actions = torch.rand(10, N, 4, generator=torch.Generator().manual_seed(0)) * 2 - 1
    for a in actions:
        recorded, kept = obs, obs.clone()  # skrl records `recorded` after the step
        obs, reward, terminated, truncated, _ = env.step(a)
        out = raw.step(a)
        assert torch.equal(recorded, kept) and recorded.data_ptr() != obs.data_ptr()
        assert obs.shape == (N, 3 * 16 * 4) and torch.equal(obs, out.obs.reshape(N, -1))
        assert reward.shape == truncated.shape == terminated.shape == (N, 1)
        assert torch.equal(reward[:, 0], out.reward) and torch.equal(truncated[:, 0], out.truncated)
    with pytest.raises(ValueError, match="intact through the next step"):
        SkrlEnv(NaviVectorEnv(raw, final_obs=False))
