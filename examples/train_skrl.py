"""Train a drone on Navi scenes with skrl's PPO, then compare it with random flight.

navi scenes generate --out scenes/ --count 4 --families rooms,hall
navi corpus build scenes/ --out corpus/ --resolution 64
python examples/train_skrl.py --corpus corpus/ --actors 64 --steps 3072
python examples/train_skrl.py --corpus corpus/ --actors 2048 --steps 10000 --device cuda --full-view
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium
import torch
from common import against_random, arguments
from skrl.agents.torch.ppo import PPO, PPO_CFG
from skrl.memories.torch import RandomMemory
from skrl.models.torch import DeterministicMixin, GaussianMixin, Model
from skrl.resources.preprocessors.torch import RunningStandardScaler
from skrl.trainers.torch import SequentialTrainer
from skrl.utils import set_seed
from torch import nn

from navi_env.config import EnvConfig
from navi_env.ecosystem.gym import make_vector_env
from navi_env.ecosystem.skrl import SkrlEnv


def mlp(inputs: int, outputs: int) -> nn.Sequential:
    layers = [nn.Linear(inputs, 128), nn.Tanh(), nn.Linear(128, 128), nn.Tanh(), nn.Linear(128, outputs)]
    return nn.Sequential(*layers)


class Policy(GaussianMixin, Model):
    def __init__(self, obs: gymnasium.Space, action: gymnasium.Space, device: torch.device) -> None:
        Model.__init__(self, observation_space=obs, action_space=action, device=device)
        GaussianMixin.__init__(self, clip_actions=True)
        self.net = nn.Sequential(mlp(self.num_observations, self.num_actions), nn.Tanh())  # mean in [-1, 1]
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


def train(corpus: str, actors: int, steps: int, config: EnvConfig, device: str = "cpu") -> Callable:
    """PPO for `steps` steps of `actors` drones; returns the mean action: obs (N, 3, Az, El) -> (N, 4)."""
    set_seed(0)
    env = SkrlEnv(make_vector_env(actors, corpus, device, config), seed=0)  # skrl flattens observations
    spaces = {"observation_space": env.observation_space, "action_space": env.action_space}
    models = {"policy": Policy(*spaces.values(), env.device), "value": Value(*spaces.values(), env.device)}
    cfg = PPO_CFG(rollouts=32, learning_epochs=4, mini_batches=4, learning_rate=1e-3, value_clip=0.0)
    cfg.value_loss_scale = 1.0
    # returns standardised for the value head: a crash costs up to 4.5 while a step earns hundredths
    cfg.value_preprocessor = RunningStandardScaler
    cfg.value_preprocessor_kwargs = {"size": 1, "device": env.device}
    cfg.experiment.write_interval = cfg.experiment.checkpoint_interval = 0  # no TensorBoard, no checkpoints
    memory = RandomMemory(memory_size=cfg.rollouts, num_envs=actors, device=env.device)
    agent = PPO(models=models, memory=memory, **spaces, device=env.device, cfg=cfg)
    trainer = {"timesteps": steps, "headless": True, "close_environment_at_exit": False}
    SequentialTrainer(env=env, agents=agent, cfg=trainer).train()
    return lambda obs: models["policy"].net(obs.flatten(1))


if __name__ == "__main__":
    args, config = arguments(__doc__, steps=3072)
    act = train(args.corpus, args.actors, args.steps, config, args.device)
    against_random(args.corpus, "skrl PPO", act, config, args.device)
