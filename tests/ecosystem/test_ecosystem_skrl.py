"""The skrl adapter hands skrl flat views of the vector env's tensors: observations (N, 3·Az·El) that
stay intact while skrl records them after the next step, (N, 1) rewards and flags, single spaces; over a
larger view, the pooled 16 x 4 view an MLP reads."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from navi_env.ecosystem.batch import MLP_VIEW, make_batched_env, pool_view
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


def test_skrl_env_pools_a_larger_view_to_the_mlp_view(corpus: Path) -> None:
    """Over a 64 x 12 env SkrlEnv hands out the pooled 16 x 4 view of the env's observation (a new tensor
    every step, so the one skrl records after stepping is intact), in a (3, 16, 4) space."""
    wide = replace(SMALL_VIEW, azimuth_bins=64, elevation_bins=12)
    vector = make_vector_env(N, corpus, config=wide)
    assert isinstance(vector, NaviVectorEnv)
    env = SkrlEnv(vector, seed=3)
    raw = make_batched_env(corpus, N, "cpu", wide)
    assert env.observation_space.shape == (3, *MLP_VIEW)
    obs, _ = env.reset()
    assert torch.equal(obs, pool_view(raw.reset(seed=3), MLP_VIEW).reshape(N, -1))
    for a in torch.rand(6, N, 4, generator=torch.Generator().manual_seed(1)) * 2 - 1:
        recorded, kept = obs, obs.clone()
        obs, reward, _, _, _ = env.step(a)
        out = raw.step(a)
        assert torch.equal(recorded, kept) and obs.shape == (N, 3 * 16 * 4)
        assert torch.equal(obs, pool_view(out.obs, MLP_VIEW).reshape(N, -1))
        assert torch.equal(reward[:, 0], out.reward)
    assert SkrlEnv(vector, view=None).observation_space.shape == (3, 64, 12)
