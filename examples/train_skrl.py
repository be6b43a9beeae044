"""Train a drone on Navi scenes with skrl's PPO, then compare it with random flight and the reactive avoider.

On a CPU, four rooms and halls at 64³:
navi scenes generate --out scenes/ --count 4 --families rooms,hall
navi corpus build scenes/ --out corpus/ --resolution 64
python examples/train_skrl.py --corpus corpus/ --actors 64 --steps 3072

On a GPU, twenty scenes of the ten unscaled families at 256³, judged on ten others it never saw (the trainers table's
split, docs/ENVIRONMENT.md):
navi scenes generate --out scenes-gpu/ --count 20 --families rooms,corridors,hall,maze,caves,forest,building,yard,arena,platforms
navi scenes generate --out unseen-gpu/ --count 10 --seed 7 --families rooms,corridors,hall,maze,caves,forest,building,yard,arena,platforms
navi corpus build scenes-gpu/ --out corpus-gpu/ --resolution 256 --device cuda
navi corpus build unseen-gpu/ --out unseen-corpus-gpu/ --resolution 256 --device cuda
python examples/train_skrl.py --corpus corpus-gpu/ --unseen unseen-corpus-gpu/ --actors 2048 --steps 8192 --device cuda --full-view

skrl's PPO as Isaac Lab configures it: an ELU MLP with a Gaussian head (the env clamps actions to
[-1, 1]), observations and returns standardised by skrl's RunningStandardScaler, the learning rate
adapted to a KL target, 5 epochs of 4 minibatches per rollout of 32 steps. The MLP reads SkrlEnv's
pooled 16 x 4 view (192 inputs) whatever the traced resolution.
"""

from __future__ import annotations

import math

import gymnasium
import torch
from common import Learner, MeanAction, main
from skrl.agents.torch.ppo import PPO, PPO_CFG
from skrl.memories.torch import RandomMemory
from skrl.models.torch import DeterministicMixin, GaussianMixin, Model
from skrl.resources.preprocessors.torch import RunningStandardScaler
from skrl.resources.schedulers.torch import KLAdaptiveLR
from skrl.trainers.torch import SequentialTrainer
from skrl.utils import set_seed
from torch import nn

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import MLP_VIEW
from navi_env.ecosystem.gym import NaviVectorEnv, make_vector_env
from navi_env.ecosystem.skrl import SkrlEnv
from navi_learner.evaluation.baselines import EvalPolicy

HIDDEN = 128
ROLLOUT = 32


def mlp(inputs: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inputs, HIDDEN), nn.ELU(), nn.Linear(HIDDEN, HIDDEN), nn.ELU(), nn.Linear(HIDDEN, outputs)
    )


class Policy(GaussianMixin, Model):
    def __init__(self, obs: gymnasium.Space, action: gymnasium.Space, device: torch.device) -> None:
        Model.__init__(self, observation_space=obs, action_space=action, device=device)
        GaussianMixin.__init__(
            self, clip_actions=False, clip_log_std=True, min_log_std=-20.0, max_log_std=2.0
        )
        self.net = mlp(self.num_observations, self.num_actions)
        self.log_std = nn.Parameter(torch.zeros(self.num_actions))

    def compute(self, inputs: dict, role: str = "") -> tuple[torch.Tensor, dict]:
        return self.net(inputs["observations"]), {"log_std": self.log_std}


class Value(DeterministicMixin, Model):
    def __init__(self, obs: gymnasium.Space, action: gymnasium.Space, device: torch.device) -> None:
        Model.__init__(self, observation_space=obs, action_space=action, device=device)
        DeterministicMixin.__init__(self)
        self.net = mlp(self.num_observations, 1)

    def compute(self, inputs: dict, role: str = "") -> tuple[torch.Tensor, dict]:
        return self.net(inputs["observations"]), {}


def ppo_config(device: torch.device, observations: gymnasium.Space) -> PPO_CFG:
    cfg = PPO_CFG(rollouts=ROLLOUT, learning_epochs=5, mini_batches=4, learning_rate=1e-3)
    cfg.learning_rate_scheduler = KLAdaptiveLR
    cfg.learning_rate_scheduler_kwargs = {"kl_threshold": 0.008}
    cfg.observation_preprocessor = RunningStandardScaler
    cfg.observation_preprocessor_kwargs = {"size": observations, "device": device}
    cfg.value_preprocessor = RunningStandardScaler
    cfg.value_preprocessor_kwargs = {"size": 1, "device": device}
    cfg.grad_norm_clip, cfg.value_loss_scale = 1.0, 2.0
    cfg.experiment.write_interval = cfg.experiment.checkpoint_interval = 0  # no TensorBoard, no checkpoints
    return cfg


class SkrlLearner:
    """skrl's PPO over SkrlEnv (the example's Learner)."""

    name = "skrl PPO"
    rollout = ROLLOUT

    def __init__(
        self, corpus: str, actors: int, config: EnvConfig, device: str = "cpu", seed: int = 0
    ) -> None:
        set_seed(seed)
        vector = make_vector_env(actors, corpus, device, config)
        assert isinstance(vector, NaviVectorEnv)
        self.env = SkrlEnv(vector, seed=seed, view=MLP_VIEW)  # obs (N, 3·16·4), the pooled view
        spaces = (self.env.observation_space, self.env.action_space)
        dev = self.env.device
        self.actor = Policy(*spaces, dev)
        self.models: dict[str, Model] = {"policy": self.actor, "value": Value(*spaces, dev)}
        inputs = self.actor.num_observations
        self.encoder = (
            f"MLP {HIDDEN}-{HIDDEN} over the pooled {MLP_VIEW[0]} x {MLP_VIEW[1]} view ({inputs} inputs)"
        )
        cfg = ppo_config(dev, self.env.observation_space)
        memory = RandomMemory(memory_size=cfg.rollouts, num_envs=actors, device=dev)
        self.agent = PPO(
            models=self.models,
            memory=memory,
            observation_space=spaces[0],
            action_space=spaces[1],
            device=dev,
            cfg=cfg,
        )
        run = {"timesteps": ROLLOUT, "headless": True, "close_environment_at_exit": False}
        self.trainer = SequentialTrainer(
            env=self.env, agents=self.agent, cfg=run | {"disable_progressbar": True}
        )

    def learn(self, steps: int) -> None:
        self.trainer.cfg.timesteps = math.ceil(steps / ROLLOUT) * ROLLOUT  # whole rollouts
        self.trainer.train()

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """The mean action (N, 4) of the env's observations obs (N, 3, Az, El)."""
        flat = self.env.flat(obs)  # (N, 3·16·4)
        standardise = self.agent.checkpoint_modules["observation_preprocessor"]  # the RunningStandardScaler
        return self.actor.net(standardise(flat))

    def policy(self) -> EvalPolicy:
        return MeanAction(self.name, self.act)


def train(
    corpus: str, actors: int, steps: int, config: EnvConfig, device: str = "cpu", seed: int = 0
) -> EvalPolicy:
    """PPO for `steps` steps of `actors` drones; returns the trained policy's mean action."""
    learner = SkrlLearner(corpus, actors, config, device, seed)
    learner.learn(steps)
    return learner.policy()


def make(corpus: str, actors: int, config: EnvConfig, device: str = "cpu", seed: int = 0) -> Learner:
    return SkrlLearner(corpus, actors, config, device, seed)


if __name__ == "__main__":
    main(__doc__, make)
