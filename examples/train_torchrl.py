"""Train a drone on Navi scenes with TorchRL's PPO (ClipPPOLoss, GAE), then compare it with random flight.

navi scenes generate --out scenes/ --count 4 --families rooms,hall
navi corpus build scenes/ --out corpus/ --resolution 64
python examples/train_torchrl.py --corpus corpus/ --actors 64 --steps 3072
python examples/train_torchrl.py --corpus corpus/ --actors 2048 --steps 10000 --device cuda --full-view
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from common import against_random, arguments
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from navi_env.config import EnvConfig
from navi_env.ecosystem.torchrl import make_torchrl_env


def mlp(inputs: int, outputs: int) -> nn.Sequential:
    layers = [nn.Linear(inputs, 128), nn.Tanh(), nn.Linear(128, 128), nn.Tanh(), nn.Linear(128, outputs)]
    return nn.Sequential(nn.Flatten(-3), *layers)  # (..., 3, Az, El) -> (..., outputs)


def train(corpus: str, actors: int, steps: int, config: EnvConfig, device: str = "cpu") -> Callable:
    """PPO for `steps` steps of `actors` drones; returns the mean action: obs (N, 3, Az, El) -> (N, 4)."""
    torch.manual_seed(0)
    env = make_torchrl_env(actors, corpus, device, config, info=False, seed=0)
    inputs, rollout = 3 * config.azimuth_bins * config.elevation_bins, 32
    net = nn.Sequential(mlp(inputs, 8), NormalParamExtractor()).to(device)  # loc (4), scale (4)
    head = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    distribution = {"distribution_class": TanhNormal, "return_log_prob": True}
    actor = ProbabilisticActor(head, ["loc", "scale"], spec=env.action_spec, **distribution)
    critic = ValueOperator(mlp(inputs, 1), in_keys=["observation"]).to(device)
    batch_frames = actors * rollout
    frames = {"frames_per_batch": batch_frames, "total_frames": actors * steps}
    collector = Collector(env, actor, **frames, auto_register_policy_transforms=False)
    advantage = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=True)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.0, critic_coeff=1.0)
    optimizer = torch.optim.Adam(loss.parameters(), lr=1e-3)
    storage = LazyTensorStorage(batch_frames, device=device)
    batches = ReplayBuffer(storage=storage, sampler=SamplerWithoutReplacement(), batch_size=batch_frames // 4)
    for batch in collector:
        with torch.no_grad():
            advantage(batch)
        batches.extend(batch.reshape(-1))
        for _ in range(4 * 4):  # 4 epochs of 4 minibatches
            parts = loss(batches.sample())
            optimizer.zero_grad()
            (parts["loss_objective"] + parts["loss_critic"] + parts["loss_entropy"]).backward()
            nn.utils.clip_grad_norm_(loss.parameters(), 0.5)
            optimizer.step()
    collector.shutdown()
    return lambda obs: torch.tanh(net(obs)[0])  # TanhNormal's location through its tanh


if __name__ == "__main__":
    args, config = arguments(__doc__, steps=3072)
    act = train(args.corpus, args.actors, args.steps, config, args.device)
    against_random(args.corpus, "TorchRL PPO", act, config, args.device)
