"""The TorchRL adapter: specs that TorchRL's own checker accepts, the batched env's values under the
same seed and actions, TorchRL's autoreset convention (final view in "next", next episode's first
observation after the partial reset) and rollouts whose steps stay intact, on the env's own view and on
the pooled view an MLP reads."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase
from torchrl.envs.utils import check_env_specs

from navi_env.ecosystem.batch import MLP_VIEW, make_batched_env, pool_view
from navi_env.ecosystem.torchrl import FLAGS, VALUES, make_torchrl_env
from navi_env.sim.rewards import TERMS

from .conftest import SMALL_VIEW

pytestmark = pytest.mark.usefixtures("single_thread")
N = 8
SHORT = replace(SMALL_VIEW, max_steps_per_episode=12)


def random_actions(steps: int, seed: int = 0) -> torch.Tensor:
    """(T, N, 4) uniform in [-1, 1]."""
    return torch.rand(steps, N, 4, generator=torch.Generator().manual_seed(seed)) * 2 - 1


@pytest.mark.parametrize(("info", "obstacles"), [(True, 0), (False, 0), (True, 2)])
def test_check_env_specs_passes(corpus: Path, info: bool, obstacles: int) -> None:
    env = make_torchrl_env(N, corpus, config=SHORT, info=info, obstacles=obstacles)
    check_env_specs(env, seed=3)
    assert env.batch_size == torch.Size([N]) and env.action_spec.shape == (N, 4)
    assert (
        ("info", "collision") in env.observation_spec.keys(True)
        if info
        else "info" not in env.observation_spec
    )


def test_step_and_maybe_reset_matches_the_batched_env_and_keeps_torchrl_conventions(corpus: Path) -> None:
    env = make_torchrl_env(N, corpus, config=SHORT, seed=9)
    raw = make_batched_env(corpus, N, "cpu", SHORT)
    td = env.reset()
    assert torch.equal(td["observation"], raw.reset(seed=9))
    ended_total = 0
    for actions in random_actions(30, seed=4):
        td.set("action", actions)
        before = td["observation"].clone()
        data, td = env.step_and_maybe_reset(td)
        out = raw.step(actions)
        ended = out.truncated
        nxt = data["next"]
        assert torch.equal(nxt["reward"][:, 0], out.reward) and torch.equal(nxt["truncated"][:, 0], ended)
        assert torch.equal(nxt["done"][:, 0], ended) and not nxt["terminated"].any()
        for key in FLAGS + VALUES:
            assert torch.equal(nxt["info", key], out.info[key]), key
        assert torch.allclose(sum(nxt["reward_terms", k] for k in TERMS), out.reward, atol=1e-6)
        keep = ~ended[:, None, None, None]
        assert torch.equal(nxt["observation"], torch.where(keep, out.obs, before))  # final view where ended
        assert torch.equal(td["observation"], out.obs)  # the next episode's first where ended
        assert not td["done"].any()
        ended_total += int(ended.sum())
    assert ended_total >= 2 * N


def test_rollout_steps_stay_intact_and_seeds_replay(corpus: Path) -> None:
    env = make_torchrl_env(N, corpus, config=SHORT)
    actions = random_actions(20, seed=6)
    step = iter(actions)

    def policy(td: TensorDict) -> TensorDict:
        return td.set("action", next(step))

    env.set_seed(21)
    rollout = env.rollout(
        20, policy, break_when_any_done=False
    )  # (N, T): TorchRL stacks the steps at the end
    raw = make_batched_env(corpus, N, "cpu", SHORT)
    raw.reset(seed=21)
    for t in range(20):
        out = raw.step(actions[t])
        assert torch.equal(rollout["next", "reward"][:, t, 0], out.reward)
        where = ~out.truncated[:, None, None, None]
        assert torch.equal(
            rollout["next", "observation"][:, t][where.expand_as(out.obs)], out.obs[where.expand_as(out.obs)]
        )
    step = iter(actions)
    env.set_seed(21)
    again = env.rollout(20, policy, break_when_any_done=False)
    assert torch.equal(again["next", "observation"], rollout["next", "observation"])


def test_maybe_reset_gives_what_the_generic_partial_reset_gives(corpus: Path) -> None:
    """The adapter's maybe_reset (one copy of the env's observation) against EnvBase.maybe_reset
    (TorchRL's reset through _reset and its masked merge) on the same steps: every root entry equal
    (but the action, which the generic merge zeroes where it reset and the policy replaces), and the
    step's "next" entries untouched."""
    fast = make_torchrl_env(N, corpus, config=SHORT, seed=5)
    generic = make_torchrl_env(N, corpus, config=SHORT, seed=5)
    td_fast, td_generic = fast.reset(), generic.reset()
    for env in (fast, generic):
        env.env.steps.copy_(torch.arange(N) % 12)  # episodes at every stage: partial resets
    merged = 0
    for actions in random_actions(26, seed=8):
        data_fast = fast.step(td_fast.set("action", actions))
        data_generic = generic.step(td_generic.set("action", actions))
        kept = data_fast["next"].clone()
        td_fast = fast.maybe_reset(fast._step_mdp(data_fast))
        td_generic = EnvBase.maybe_reset(generic, generic._step_mdp(data_generic))
        keys = set(td_generic.keys(True, True)) - {"action"}  # the policy writes the next action anyway
        assert keys == set(td_fast.keys(True, True)) - {"action"}
        assert all(torch.equal(td_fast[k], td_generic[k]) for k in keys), keys
        assert (data_fast["next"] == kept).all()
        merged += int(kept["done"].any() and not kept["done"].all())
    assert merged >= 10


def test_pooled_view_keeps_specs_and_conventions(corpus: Path) -> None:
    """With view=MLP_VIEW over a 32 x 8 env: specs TorchRL accepts, the pooled view of the env's
    observation, the pooled final view in "next" where an episode ended, and the pooled first view of
    the next episode after the partial reset."""
    wide = replace(SHORT, azimuth_bins=32, elevation_bins=8)
    env = make_torchrl_env(N, corpus, config=wide, seed=9, view=MLP_VIEW)
    check_env_specs(env, seed=3)
    assert env.observation_spec["observation"].shape == (N, 3, *MLP_VIEW)
    raw = make_batched_env(corpus, N, "cpu", wide)
    env.set_seed(9)
    td = env.reset()
    assert torch.equal(td["observation"], pool_view(raw.reset(seed=9), MLP_VIEW))
    ended_total = 0
    for actions in random_actions(26, seed=3):
        before = td["observation"].clone()  # (N, 3, 16, 4)
        data, td = env.step_and_maybe_reset(td.set("action", actions))
        out = raw.step(actions)
        now = pool_view(out.obs, MLP_VIEW)  # (N, 3, 16, 4)
        keep = ~out.truncated[:, None, None, None]
        assert torch.equal(data["next", "observation"], torch.where(keep, now, before))
        assert torch.equal(td["observation"], now)
        ended_total += int(out.truncated.sum())
    assert ended_total >= N
