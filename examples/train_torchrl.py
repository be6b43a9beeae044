"""Train a drone on Navi scenes with TorchRL's PPO (ClipPPOLoss, GAE), then compare it with random flight
and the reactive avoider.

On a CPU, four rooms and halls at 64³:
navi scenes generate --out scenes/ --count 4 --families rooms,hall
navi corpus build scenes/ --out corpus/ --resolution 64
python examples/train_torchrl.py --corpus corpus/ --actors 64 --steps 3072

On a GPU, twenty scenes of the ten unscaled families at 256³, judged on ten others it never saw (the trainers table's
split, docs/ENVIRONMENT.md):
navi scenes generate --out scenes-gpu/ --count 20 --families rooms,corridors,hall,maze,caves,forest,building,yard,arena,platforms
navi scenes generate --out unseen-gpu/ --count 10 --seed 7 --families rooms,corridors,hall,maze,caves,forest,building,yard,arena,platforms
navi corpus build scenes-gpu/ --out corpus-gpu/ --resolution 256 --device cuda
navi corpus build unseen-gpu/ --out unseen-corpus-gpu/ --resolution 256 --device cuda
python examples/train_torchrl.py --corpus corpus-gpu/ --unseen unseen-corpus-gpu/ --actors 2048 --steps 8192 --device cuda --full-view

A Collector over NaviTorchRLEnv's pooled 16 x 4 view (view=MLP_VIEW: 192 inputs whatever the traced
resolution), a TanhNormal actor and a critic (Tanh MLPs), GAE, ClipPPOLoss and a replay buffer of one
batch: 4 epochs of 4 minibatches per rollout of 32 steps. Both networks standardise the view with
per-input statistics of a random-flight rollout, as TorchRL's ObservationNorm.init_stats computes them.
"""

from __future__ import annotations

import math

import torch
from common import Learner, MeanAction, main
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import MLP_VIEW, pool_view
from navi_env.ecosystem.torchrl import make_torchrl_env
from navi_learner.evaluation.baselines import EvalPolicy

HIDDEN = 128
ROLLOUT = 32


class Standardise(nn.Module):
    """(x - loc) / scale per input of a view (..., 3, Az', El'), flattened to (..., 3·Az'·El')."""

    loc: torch.Tensor
    scale: torch.Tensor

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("loc", loc.flatten())  # (3·Az'·El',)
        self.register_buffer("scale", scale.flatten())  # (3·Az'·El',)

    def forward(self, view: torch.Tensor) -> torch.Tensor:
        return (view.flatten(-3) - self.loc) / self.scale  # (..., 3·Az'·El')


def mlp(norm: Standardise, outputs: int) -> nn.Sequential:
    inputs = norm.loc.numel()
    layers = [
        nn.Linear(inputs, HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, outputs),
    ]
    return nn.Sequential(norm, *layers)  # (..., 3, Az', El') -> (..., outputs)


class TorchRLLearner:
    """TorchRL's PPO over NaviTorchRLEnv (the example's Learner)."""

    name = "TorchRL PPO"
    rollout = ROLLOUT

    def __init__(
        self, corpus: str, actors: int, config: EnvConfig, device: str = "cpu", seed: int = 0
    ) -> None:
        torch.manual_seed(seed)
        self.env = make_torchrl_env(actors, corpus, device, config, info=False, seed=seed, view=MLP_VIEW)
        self.actors = actors
        with torch.no_grad():
            views = self.env.rollout(ROLLOUT, break_when_any_done=False)["observation"]  # (N, T, 3, 16, 4)
        loc, scale = views.mean(dim=(0, 1)), views.std(dim=(0, 1)).clamp_min(1e-2)  # (3, 16, 4) each
        self.net = nn.Sequential(mlp(Standardise(loc, scale), 8), NormalParamExtractor()).to(device)
        # self.net: loc (4) and scale (4) of the TanhNormal
        head = TensorDictModule(self.net, in_keys=["observation"], out_keys=["loc", "scale"])
        distribution = {"distribution_class": TanhNormal, "return_log_prob": True}
        actor = ProbabilisticActor(head, ["loc", "scale"], spec=self.env.action_spec, **distribution)
        critic = ValueOperator(mlp(Standardise(loc, scale), 1), in_keys=["observation"]).to(device)
        self.encoder = (
            f"MLP {HIDDEN}-{HIDDEN} over the pooled {MLP_VIEW[0]} x {MLP_VIEW[1]} view ({loc.numel()} inputs)"
        )
        self.actor, self.critic = actor, critic
        self.advantage = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=True)
        self.loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.0, critic_coeff=1.0)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=1e-3)
        frames = actors * ROLLOUT
        storage = LazyTensorStorage(frames, device=device)
        self.batches = ReplayBuffer(
            storage=storage, sampler=SamplerWithoutReplacement(), batch_size=frames // 4
        )
        collector = Collector(
            self.env, actor, frames_per_batch=frames, total_frames=-1, auto_register_policy_transforms=False
        )  # endless: learn() takes the rollouts it needs
        self.rollouts = iter(collector)

    def learn(self, steps: int) -> None:
        for _ in range(math.ceil(steps / ROLLOUT)):  # whole rollouts
            batch = next(self.rollouts)  # (N, T) TensorDict of one rollout
            with torch.no_grad():
                self.advantage(batch)
            self.batches.extend(batch.reshape(-1))
            for _ in range(4 * 4):  # 4 epochs of 4 minibatches
                parts = self.loss(self.batches.sample())
                self.optimizer.zero_grad()
                (parts["loss_objective"] + parts["loss_critic"] + parts["loss_entropy"]).backward()
                nn.utils.clip_grad_norm_(self.loss.parameters(), 0.5)
                self.optimizer.step()

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """The mean action (N, 4) of the env's observations obs (N, 3, Az, El): TanhNormal's location
        through its tanh."""
        view = obs if self.env.view is None else pool_view(obs, self.env.view)  # (N, 3, 16, 4)
        return torch.tanh(self.net(view)[0])

    def policy(self) -> EvalPolicy:
        return MeanAction(self.name, self.act)


def train(
    corpus: str, actors: int, steps: int, config: EnvConfig, device: str = "cpu", seed: int = 0
) -> EvalPolicy:
    """PPO for `steps` steps of `actors` drones; returns the trained policy's mean action."""
    learner = TorchRLLearner(corpus, actors, config, device, seed)
    learner.learn(steps)
    return learner.policy()


def make(corpus: str, actors: int, config: EnvConfig, device: str = "cpu", seed: int = 0) -> Learner:
    return TorchRLLearner(corpus, actors, config, device, seed)


if __name__ == "__main__":
    main(__doc__, make)
