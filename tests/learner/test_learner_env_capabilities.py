"""The env capabilities the learner and the baselines read: derived from an env in one place, with the
defaults of an env that offers none."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from navi_learner.envs.protocol import EnvCapabilities, capabilities
from navi_learner.envs.toy import ToyEnv
from navi_learner.evaluation.baselines import (
    ReactiveConfig,
    ReactivePolicy,
    goal_seeker_for_env,
    reactive_for_env,
)


def drone_like(task: str = "explore", goal_bank: object | None = None) -> SimpleNamespace:
    """An env with the drone env's optional members (navi_env.sim.env.SdfDagEnv)."""
    config = SimpleNamespace(
        task=task,
        horizon=12.0,
        dt=0.05,
        sensor=SimpleNamespace(elevation_min_deg=-30.0, elevation_max_deg=45.0),
        reward=SimpleNamespace(shaping_gamma=0.97),
    )
    corpus = SimpleNamespace(infos=[SimpleNamespace(name="hall"), SimpleNamespace(name="maze")])
    return SimpleNamespace(
        config=config, compact_obs=True, goal_marks=goal_bank is not None, goal_bank=goal_bank, corpus=corpus
    )


def test_an_env_without_optional_members_has_the_defaults() -> None:
    assert capabilities(object()) == EnvCapabilities()


def test_the_toy_env_offers_its_horizon_only() -> None:
    assert capabilities(ToyEnv(2)) == EnvCapabilities(horizon=10.0)


def test_a_drone_env_offers_every_capability() -> None:
    caps = capabilities(drone_like("pointgoal", goal_bank=object()))
    assert caps == EnvCapabilities(
        compact_obs=True,
        goal_marks=True,
        goal_paths=True,
        task="pointgoal",
        shaping_gamma=0.97,
        horizon=12.0,
        elevation_deg=(-30.0, 45.0),
        dt=0.05,
        scenes=("hall", "maze"),
    )


def test_the_reactive_baseline_follows_the_capabilities() -> None:
    assert reactive_for_env(object()).cfg == ReactivePolicy().cfg
    toy = reactive_for_env(ToyEnv(2)).cfg
    assert (toy.horizon, toy.elevation_min, toy.elevation_max) == (10.0, -90.0, 90.0)
    drone = reactive_for_env(drone_like()).cfg
    assert (drone.horizon, drone.elevation_min, drone.elevation_max) == (12.0, -30.0, 45.0)


def test_the_goal_seekers_need_a_point_goal_drone_env() -> None:
    for env in (ToyEnv(2), drone_like("explore")):
        with pytest.raises(ValueError, match="point-goal"):
            goal_seeker_for_env("greedy", env)
    greedy = goal_seeker_for_env("greedy", drone_like("pointgoal"))
    assert greedy.cfg.avoid == ReactiveConfig(horizon=12.0, elevation_min=-30.0, elevation_max=45.0)
    with pytest.raises(ValueError, match="oracle"):
        goal_seeker_for_env("oracle", drone_like("pointgoal"))
