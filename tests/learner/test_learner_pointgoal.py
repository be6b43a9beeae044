"""PPO learns point-goal episodes from the goal mark alone: on a toy room, a short CPU run reaches the
goal far more often than random flight, with the engine unchanged."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from navi_env.config import EnvConfig, GoalConfig, RewardConfig
from navi_env.sim.env import SdfDagEnv
from navi_env.tracer.scene import load_corpus
from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.evaluation.baselines import RandomPolicy
from navi_learner.evaluation.evaluate import CheckpointPolicy, evaluate
from navi_learner.ppo.train import train

from ..env.test_env_env import room_gmdag

pytestmark = pytest.mark.usefixtures("single_thread")

TOY = EnvConfig(
    task="pointgoal",
    azimuth_bins=32,
    elevation_bins=8,
    max_steps_per_episode=40,
    goal=GoalConfig(near=1.5, far=4.0, radius=1.0, stop_speed=5.0, mark_degrees=30.0),
    reward=RewardConfig(progress_weight=2.0),
)
"""A toy task: goals 1.5-4 m from the room's centre, reached within 1 m at any speed, a wide mark, and
progress paid four times the default so that a short run feels it."""


def room(actors: int, seed: int) -> SdfDagEnv:
    corpus = load_corpus([room_gmdag()], "cpu")
    return SdfDagEnv(corpus, actors, "cpu", TOY, spawns=[torch.tensor([[8.0, 8.0, 4.0]])], seed=seed)


def test_ppo_learns_to_reach_goals_it_only_sees_in_the_observation(tmp_path: Path) -> None:
    """131,072 steps of PPO reach at least 80% of the toy room's goals, well above random flight's rate."""
    ppo = PPOConfig(
        lr=1e-3, num_minibatches=2, bptt_chunk=16, ppo_epochs=4, ent_coef=0.0,
        intrinsic_rnd_weight=0.0, intrinsic_episodic_weight=0.0,
    )  # fmt: skip
    cfg = TrainConfig(
        n_actors=64, rollout_length=16, total_steps=131_072, engine=EngineConfig.tiny(), ppo=ppo,
        checkpoint_every=10**9, log_every=8, task="pointgoal",
    )  # fmt: skip
    result = train(room(64, 1), cfg, run_dir=tmp_path / "run", progress=False)
    trained = evaluate(
        room(16, 5), CheckpointPolicy(result.final_checkpoint, torch.device("cpu")), 300, seed=5
    )
    rand = evaluate(room(16, 5), RandomPolicy(5), 300, seed=5)
    assert trained.task == rand.task == "pointgoal" and trained.episodes >= 100
    assert trained.success_rate >= 0.8 and trained.success_rate > rand.success_rate + 0.4, (trained, rand)
    assert trained.spl >= 0.6 and trained.ci["success_rate"][0] > rand.ci["success_rate"][1]
