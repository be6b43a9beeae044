"""The Gymnasium adapter keeps Gymnasium's contracts and the batched env's values: spaces that hold
every observation, the SAME_STEP autoreset it declares (first observation of the next episode,
final observation in info), bit-identical tensors to SdfDagEnv under the same seed and actions,
deterministic seeding, Gymnasium's own env checker on the one-drone view, NumPy copies, pictures."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, VectorEnv

import navi_env.ecosystem  # noqa: F401 (registers Navi/Explore-v0)
from navi_env.ecosystem.batch import make_batched_env
from navi_env.ecosystem.gym import NaviVectorEnv
from navi_env.ecosystem.render import colour_depth
from navi_env.sim.env import GOAL_INFO_KEYS, INFO_KEYS

from .conftest import SMALL_VIEW

pytestmark = pytest.mark.usefixtures("single_thread")
N = 8
SHORT = replace(SMALL_VIEW, max_steps_per_episode=12)
"""Episodes of 12 steps: every actor ends one within the tests' rollouts."""


def random_actions(steps: int, n: int = N, seed: int = 0) -> torch.Tensor:
    """(T, N, 4) uniform in [-1, 1]."""
    return torch.rand(steps, n, 4, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def test_make_vec_gives_a_torch_vector_env_with_declared_spaces(corpus: Path) -> None:
    env = gym.make_vec("Navi/Explore-v0", num_envs=N, corpus=corpus, device="cpu", config=SMALL_VIEW)
    assert isinstance(env, VectorEnv) and env.num_envs == N
    assert env.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    assert env.single_observation_space.shape == (3, 16, 4) and env.observation_space.shape == (N, 3, 16, 4)
    assert env.single_action_space.shape == (4,) and env.action_space.shape == (N, 4)
    assert isinstance(env.single_action_space, gym.spaces.Box)
    assert np.all(env.single_action_space.low == -1.0) and np.all(env.single_action_space.high == 1.0)
    obs, _ = env.reset(seed=0)
    assert isinstance(obs, torch.Tensor) and obs.dtype == torch.float32 and obs.device.type == "cpu"
    env.action_space.seed(0)
    for _ in range(30):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())  # NumPy actions too
        assert env.observation_space.contains(obs.numpy())
        assert reward.shape == (N,) and reward.dtype == torch.float32
        assert terminated.dtype == torch.bool and not terminated.any()  # contact never ends an episode
        assert truncated.shape == (N,) and truncated.dtype == torch.bool
        assert torch.allclose(sum(info["reward_terms"].values()), reward, atol=1e-6)
        assert info["collision"].shape == (N,) and info["collision"].dtype == torch.bool
        assert set(INFO_KEYS) <= info.keys()


@pytest.mark.parametrize("final_obs", [True, False])
def test_vector_env_and_batched_env_agree_bit_for_bit(corpus: Path, final_obs: bool) -> None:
    raw = make_batched_env(corpus, N, "cpu", SHORT)
    env = NaviVectorEnv(make_batched_env(corpus, N, "cpu", SHORT), final_obs=final_obs)
    assert torch.equal(env.reset(seed=5)[0], raw.reset(seed=5))
    ended = 0
    for actions in random_actions(40):
        obs, reward, terminated, truncated, info = env.step(actions)
        out = raw.step(actions)
        assert torch.equal(obs, out.obs) and torch.equal(reward, out.reward)
        assert torch.equal(terminated, out.done) and torch.equal(truncated, out.truncated)
        for key in INFO_KEYS:
            assert torch.equal(info[key], out.info[key]), key
        for key, term in out.reward_terms.items():
            assert torch.equal(info["reward_terms"][key], term), key
        ended += int(truncated.sum())
    assert ended >= 2 * N  # the rollout crossed episode ends


def test_same_step_autoreset_behaves_as_declared(corpus: Path) -> None:
    env = NaviVectorEnv(make_batched_env(corpus, N, "cpu", SHORT))
    obs, _ = env.reset(seed=1)
    checked = 0
    for actions in random_actions(30, seed=1):
        before = obs.clone()  # the view these actions are chosen on
        obs, _, terminated, truncated, info = env.step(actions)
        ended = terminated | truncated
        assert torch.equal(info["_final_obs"], ended) and torch.equal(info["_final_info"], ended)
        for i in torch.nonzero(ended).flatten().tolist():
            assert torch.equal(info["final_obs"][i], before[i])  # the final (last) view of the episode
            assert torch.all(obs[i, 2] == 0)  # the first observation of the next episode: no delta yet
            assert int(info["final_info"]["episode_length"][i]) == SHORT.max_steps_per_episode
            checked += 1
        for i in torch.nonzero(~ended).flatten().tolist():
            assert torch.equal(obs[i, 2], obs[i, 0] - before[i, 0])  # the same episode goes on
    assert checked >= 2 * N


def test_gymnasium_episode_statistics_match_the_env_under_same_step(corpus: Path) -> None:
    """Gymnasium's own RecordEpisodeStatistics reads metadata["autoreset_mode"]: with SAME_STEP it must
    count every step, so its returns and lengths equal the env's own at each episode end."""
    env = gym.make_vec("Navi/Explore-v0", num_envs=N, corpus=corpus, config=SHORT, numpy=True)
    env = gym.wrappers.vector.RecordEpisodeStatistics(env)
    env.reset(seed=2)
    seen = 0
    for actions in random_actions(30, seed=2).numpy():
        _, _, _, truncated, info = env.step(actions)
        if truncated.any():
            stats = info["episode"]
            assert np.array_equal(stats["l"][truncated], info["episode_length"][truncated])
            assert np.allclose(stats["r"][truncated], info["episode_return"][truncated], atol=1e-4)
            seen += int(truncated.sum())
    assert seen >= 2 * N


def test_handed_out_observations_stay_intact_through_the_next_step(corpus: Path) -> None:
    env = NaviVectorEnv(make_batched_env(corpus, N, "cpu", SMALL_VIEW))
    obs, _ = env.reset(seed=0)
    for actions in random_actions(6):
        kept = obs.clone()
        nxt, *_ = env.step(actions)
        assert torch.equal(obs, kept) and nxt.data_ptr() != obs.data_ptr()  # what skrl records after stepping
        obs = nxt
    lean = NaviVectorEnv(make_batched_env(corpus, N, "cpu", SMALL_VIEW), final_obs=False)
    obs, _ = lean.reset(seed=0)
    assert obs.data_ptr() == lean.env.obs.data_ptr()  # zero copy: the env's own buffer
    assert "final_obs" not in lean.step(random_actions(1)[0])[4]


def test_reset_seeds_are_deterministic_on_the_cpu(corpus: Path) -> None:
    def rollout(env: VectorEnv, seeds: list[int | None]) -> list[torch.Tensor]:
        frames = []
        for seed in seeds:
            frames.append(env.reset(seed=seed)[0].clone())
            for actions in random_actions(5):
                frames.append(env.step(actions)[0].clone())
        return frames

    def make() -> VectorEnv:
        return gym.make_vec("Navi/Explore-v0", num_envs=N, corpus=corpus, config=SMALL_VIEW)

    first, second = rollout(make(), [7, None, None]), rollout(make(), [7, None, None])
    assert all(torch.equal(a, b) for a, b in zip(first, second, strict=True))
    assert not torch.equal(first[0], first[6])  # reset() without a seed starts new episodes
    other = rollout(make(), [8])
    assert not torch.equal(first[0], other[0])


def test_one_drone_env_passes_gymnasium_check_env(corpus: Path, recwarn: pytest.WarningsRecorder) -> None:
    env = gym.make("Navi/Explore-v0", corpus=corpus, config=SMALL_VIEW, render_mode="rgb_array")
    check_env(env.unwrapped)
    assert not [w for w in recwarn if "gymnasium" in w.filename], [str(w.message) for w in recwarn]
    short = gym.make("Navi/Explore-v0", corpus=corpus, config=SHORT)
    obs, _ = short.reset(seed=0)
    for step in range(1, SHORT.max_steps_per_episode + 1):
        before = obs
        obs, reward, terminated, truncated, _ = short.step(short.action_space.sample())
        assert isinstance(obs, np.ndarray) and isinstance(reward, float) and not terminated
        assert truncated == (step == SHORT.max_steps_per_episode)
    assert np.array_equal(obs, before)  # the episode's final observation is its last view
    first, _ = short.reset()
    assert np.all(first[2] == 0) and first in short.observation_space  # the next episode's first


def test_numpy_env_hands_out_fresh_host_copies_of_the_same_values(corpus: Path) -> None:
    host = gym.make_vec("Navi/Explore-v0", num_envs=N, corpus=corpus, config=SHORT, numpy=True)
    device = gym.make_vec("Navi/Explore-v0", num_envs=N, corpus=corpus, config=SHORT)
    obs, _ = host.reset(seed=4)
    assert np.array_equal(obs, device.reset(seed=4)[0].numpy())
    for actions in random_actions(14):
        previous = obs
        obs, reward, _, truncated, info = host.step(actions.numpy())
        expected = device.step(actions)
        assert isinstance(obs, np.ndarray) and not np.shares_memory(obs, previous)
        assert np.array_equal(obs, expected[0].numpy()) and np.array_equal(reward, expected[1].numpy())
        assert np.array_equal(truncated, expected[3].numpy()) and isinstance(info["collision"], np.ndarray)


def test_render_shows_the_drone_view_and_where_the_drones_are(corpus: Path) -> None:
    env = NaviVectorEnv(make_batched_env(corpus, N, "cpu", SMALL_VIEW), render_mode="rgb_array")
    env.reset(seed=3)
    for actions in random_actions(3):
        env.step(actions)
    frames = env.render()
    assert frames is not None and len(frames) == N
    actor = 5
    frame = frames[actor]
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    scale = 512 // 16  # the 16 x 4 panorama scaled to 512 pixels
    view = frame[: 4 * scale : scale, ::scale][:, :16]  # (El, Az, 3) one pixel per ray
    depth = env.env.obs[actor, 0].numpy()  # (Az, El)
    assert np.array_equal(
        view[3, 8], colour_depth(depth[0, 0], 100.0)
    )  # middle column, bottom row: ahead, lowest
    assert np.array_equal(
        view[0, 4], colour_depth(depth[4, 3], 100.0)
    )  # left quarter, top row: 90 degrees left
    plan = frame[4 * scale + 4 :]
    red = np.argwhere(np.all(plan == [230, 40, 40], axis=-1))  # the chosen drone and its heading
    info = env.env.corpus.infos[int(env.env.scene[actor])]
    cell = max(np.subtract(info.bounds_max[:2], info.bounds_min[:2])) / 256
    x, y = env.env.position[actor, :2].tolist()
    row, col = (info.bounds_max[1] - y) / cell, (x - info.bounds_min[0]) / cell
    left = (plan.shape[1] - int(np.ceil((info.bounds_max[0] - info.bounds_min[0]) / cell)) - 1) // 2
    assert red.size and np.min(np.hypot(red[:, 0] - row, red[:, 1] - left - col)) < 2.0
    assert (np.all(plan == [40, 44, 52], axis=-1)).any()  # walls


def test_point_goal_id_gives_goal_episodes_through_the_same_adapters(corpus: Path) -> None:
    env = gym.make_vec("Navi/PointGoal-v0", num_envs=N, corpus=corpus, device="cpu", config=SMALL_VIEW)
    assert isinstance(env.unwrapped, NaviVectorEnv)
    raw = env.unwrapped.env  # the SdfDagEnv under the adapter
    assert raw.config.task == "pointgoal" and raw.config.max_steps_per_episode == 500
    obs, _ = env.reset(seed=0)
    assert bool((obs[:, 1] < 0).flatten(1).any(dim=1).all())  # every drone sees its goal mark
    env.action_space.seed(0)
    for _ in range(20):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs.numpy())
        assert torch.allclose(sum(info["reward_terms"].values()), reward, atol=1e-6)
        assert not bool((terminated & truncated).any())  # an episode ends one way
        assert set(GOAL_INFO_KEYS) <= info.keys() and "progress" in info["reward_terms"]
        assert torch.equal(terminated, info["success"])
    single = gym.make("Navi/PointGoal-v0", corpus=corpus, config=SMALL_VIEW)
    check_env(single.unwrapped)
