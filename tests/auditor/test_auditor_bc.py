"""Behavioural cloning from demonstrations of the scripted reactive controller on the learner's toy env.

The demonstrations are real flights: navi_learner's ReactivePolicy (steer toward the most open azimuth)
flying navi_learner's ToyEnv, written and validated through navi_auditor.demos. The clone must drive
the loss down, match the controller on held-out flights far better than a random policy, earn more
reward than a random policy, and be fine-tunable by `navi train --checkpoint` with its lineage kept.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from navi_auditor.bc import BCConfig, action_error, run_bc, train_bc
from navi_auditor.demos import DemoBuffer, load_demos
from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.envs.toy import ToyEnv
from navi_learner.evaluation.baselines import RandomPolicy, reactive_for_env
from navi_learner.evaluation.evaluate import CheckpointPolicy, evaluate
from navi_learner.ppo.train import train
from navi_learner.serving.checkpoint import load_checkpoint

ENGINE = EngineConfig.tiny(head_hidden=64)

pytestmark = pytest.mark.usefixtures("single_thread")


def reactive_flights(folder: Path, actors: int, steps: int, seed: int) -> None:
    """Fly the reactive controller in the toy env and save one demonstration per actor."""
    env = ToyEnv(actors, seed=seed, max_steps=64)
    pilot = reactive_for_env(env)
    obs = env.reset(seed=seed)  # (N, 3, Az, El)
    resets = torch.ones(actors, dtype=torch.bool)  # (N,)
    buffers = [DemoBuffer(scene=f"toy-{seed}") for _ in range(actors)]
    for _ in range(steps):
        action = pilot.act(obs, resets).clamp(-1.0, 1.0)  # (N, 4)
        zeros = torch.zeros(actors)  # (N,)
        pose = torch.stack([*env.position.unbind(1), zeros, zeros, env.heading], dim=1)  # (N, 6)
        out = env.step(action)
        ended = out.done | out.truncated  # (N,) bool
        for i, buffer in enumerate(buffers):
            buffer.add(
                obs[i].numpy(), action[i].numpy(), pose[i].numpy(), float(out.reward[i]), bool(ended[i])
            )
        obs, resets = out.obs, ended
    for i, buffer in enumerate(buffers):
        buffer.save(folder / f"flight_{seed}_{i:02d}.npz")


def test_bc_clones_the_reactive_controller_and_rl_fine_tunes_it(tmp_path: Path) -> None:
    reactive_flights(tmp_path / "train", actors=8, steps=200, seed=1)
    reactive_flights(tmp_path / "held", actors=2, steps=200, seed=2)
    train_demos, held = load_demos(tmp_path / "train"), load_demos(tmp_path / "held")
    assert train_demos[0].obs_shape == (3, 16, 8) and sum(d.steps for d in train_demos) == 1600

    config = BCConfig(epochs=25, bptt=25, streams=8, lr=3e-3)
    policy, losses = train_bc(train_demos, ENGINE, config)
    assert losses[-1] < 0.2 * losses[0], losses

    cloned = action_error(policy, held, torch.device("cpu"))
    actions = np.concatenate([d.actions for d in held])  # (T, 4)
    random_error = float(np.mean((np.random.default_rng(0).uniform(-1, 1, actions.shape) - actions) ** 2))
    mean_error = float(np.mean((actions - np.concatenate([d.actions for d in train_demos]).mean(0)) ** 2))
    assert cloned < 0.2 * random_error, (cloned, random_error)
    assert cloned < 0.2 * mean_error, (cloned, mean_error)  # it reacts to the view, not just the average

    ckpt = tmp_path / "bc.pt"
    summary = run_bc(train_demos, ckpt, ENGINE, config)
    meta = load_checkpoint(ckpt).meta
    assert meta.training_source == "bc" and meta.parent_checkpoint is None and meta.step_id == 0
    assert meta.obs_shape == [3, 16, 8] and meta.temporal_core == "mamba2"
    assert float(summary["final_loss"]) < float(summary["first_loss"])

    clone_flight = evaluate(ToyEnv(16, seed=5), CheckpointPolicy(ckpt, torch.device("cpu"), 0.0), 150, seed=5)
    random_flight = evaluate(ToyEnv(16, seed=5), RandomPolicy(5), 150, seed=5)
    assert clone_flight.reward_per_step > random_flight.reward_per_step + 0.2, (clone_flight, random_flight)

    ppo = PPOConfig(lr=1e-3, num_minibatches=2, bptt_chunk=16)
    rl = TrainConfig(
        n_actors=8, rollout_length=16, total_steps=128, engine=ENGINE, ppo=ppo, checkpoint_every=10**9
    )
    tuned = train(ToyEnv(8, seed=3), rl, run_dir=tmp_path / "rl", resume_from=ckpt, progress=False)
    lineage = load_checkpoint(tuned.final_checkpoint).meta
    assert lineage.parent_checkpoint == str(ckpt) and lineage.training_source == "rl"
    assert lineage.step_id == 128
