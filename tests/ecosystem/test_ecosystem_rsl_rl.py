"""The rsl_rl adapter is rsl_rl's VecEnv over the vector env: observation groups "policy" and "critic" of
the pooled view that rsl_rl's runner resolves, the batched env's rewards, dones for every ended episode
with time_outs for the truncated ones, Navi's metrics in extras["log"], and an episode_length_buf that is
the env's own step counter (writing it moves the time limits)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from rsl_rl.env import VecEnv
from rsl_rl.utils import resolve_obs_groups

from navi_env.ecosystem.batch import MLP_VIEW, make_batched_env, pool_view
from navi_env.ecosystem.gym import NaviVectorEnv, make_vector_env
from navi_env.ecosystem.rsl_rl import OBS_GROUPS, RslRlEnv

from .conftest import SMALL_VIEW

pytestmark = pytest.mark.usefixtures("single_thread")
N = 8
WIDE = replace(SMALL_VIEW, azimuth_bins=32, elevation_bins=8, max_steps_per_episode=12)


def adapter(corpus: Path, seed: int) -> RslRlEnv:
    vector = make_vector_env(N, corpus, config=WIDE)
    assert isinstance(vector, NaviVectorEnv)
    return RslRlEnv(vector, seed=seed)


def test_rsl_rl_env_steps_like_the_batched_env_with_groups_time_outs_and_logs(corpus: Path) -> None:
    env = adapter(corpus, seed=5)
    raw = make_batched_env(corpus, N, "cpu", WIDE)
    assert isinstance(env, VecEnv) and env.num_envs == N and env.num_actions == 4
    assert env.max_episode_length == 12 and env.device == torch.device("cpu")
    obs = env.get_observations()
    first = pool_view(raw.reset(seed=5), MLP_VIEW).reshape(N, -1)  # (N, 192)
    assert obs.batch_size == torch.Size([N]) and torch.equal(obs["policy"], first)
    assert torch.equal(obs["critic"], first)
    groups = resolve_obs_groups(obs, dict(OBS_GROUPS), ["actor", "critic"])
    assert groups == {"actor": ["policy"], "critic": ["critic"]}
    ended = 0
    for a in torch.rand(30, N, 4, generator=torch.Generator().manual_seed(2)) * 2 - 1:
        recorded, kept = obs["policy"], obs["policy"].clone()  # rsl_rl stores it after the step
        obs, reward, dones, extras = env.step(a)
        out = raw.step(a)
        assert torch.equal(recorded, kept)
        assert torch.equal(obs["policy"], pool_view(out.obs, MLP_VIEW).reshape(N, -1))
        assert torch.equal(reward, out.reward) and dones.dtype == torch.int64
        assert torch.equal(dones.bool(), out.done | out.truncated)
        assert torch.equal(extras["time_outs"], out.truncated)
        log = extras["log"]
        assert float(log["Navi/collisions_per_1k"]) == pytest.approx(
            1000 * out.info["collision"].float().mean().item()
        )
        assert float(log["Navi/clearance_m"]) == pytest.approx(out.info["clearance"].mean().item())
        terms = sum(float(log[f"Navi/reward_{k}"]) for k in raw.terms)
        assert terms == pytest.approx(out.reward.mean().item(), abs=1e-5)
        ended += int(dones.sum())
    assert ended >= N  # every drone's 12-step episode ended at least once


def test_episode_length_buf_is_the_env_step_counter_and_moves_the_time_limits(corpus: Path) -> None:
    env = adapter(corpus, seed=6)
    assert env.episode_length_buf is env.vector.env.steps
    env.episode_length_buf = torch.tensor([11, 0, 0, 0, 11, 0, 0, 0])  # as init_at_random_ep_len writes it
    _, _, dones, extras = env.step(torch.zeros(N, 4))
    assert extras["time_outs"].tolist() == [True, False, False, False, True, False, False, False]
    assert dones.tolist() == [1, 0, 0, 0, 1, 0, 0, 0]
    obs, _ = env.reset()
    assert int(env.episode_length_buf.sum()) == 0 and obs is env.get_observations()


def test_rsl_rl_env_needs_observations_that_survive_the_next_step(corpus: Path) -> None:
    with pytest.raises(ValueError, match="intact through the next step"):
        RslRlEnv(NaviVectorEnv(make_batched_env(corpus, N, "cpu", SMALL_VIEW), final_obs=False))
