"""Train a drone on Navi scenes with rsl_rl's PPO (OnPolicyRunner), then compare it with random flight and
the reactive avoider.

On a CPU, four rooms and halls at 64³:
navi scenes generate --out scenes/ --count 4 --families rooms,hall
navi corpus build scenes/ --out corpus/ --resolution 64
python examples/train_rsl_rl.py --corpus corpus/ --actors 64 --steps 3072
python examples/train_rsl_rl.py --corpus corpus/ --actors 64 --steps 3072 --recurrent

On a GPU, twenty scenes of the ten unscaled families at 256³, judged on ten others it never saw (the trainers table's
split, docs/ENVIRONMENT.md):
navi scenes generate --out scenes-gpu/ --count 20 --families rooms,corridors,hall,maze,caves,forest,building,yard,arena,platforms
navi scenes generate --out unseen-gpu/ --count 10 --seed 7 --families rooms,corridors,hall,maze,caves,forest,building,yard,arena,platforms
navi corpus build scenes-gpu/ --out corpus-gpu/ --resolution 256 --device cuda
navi corpus build unseen-gpu/ --out unseen-corpus-gpu/ --resolution 256 --device cuda
python examples/train_rsl_rl.py --corpus corpus-gpu/ --unseen unseen-corpus-gpu/ --actors 2048 --steps 8192 --device cuda --full-view

rsl_rl's PPO with its own defaults (5 epochs of 4 minibatches per rollout, the learning rate adapted to
a KL target of 0.01, entropy bonus 0.01, time-outs bootstrapped from the value) and rollouts of 32 steps;
an ELU MLP actor and critic (a GRU in front of each with --recurrent) with rsl_rl's empirical
observation normalisation, reading RslRlEnv's pooled 16 x 4 view (192 inputs) whatever the traced
resolution. The first rollout starts the actors at random points of their episodes
(init_at_random_ep_len), so their time limits do not all fall on one step.
"""

from __future__ import annotations

import copy
import math

import torch
from common import Learner, main
from rsl_rl.models import MLPModel
from rsl_rl.runners import OnPolicyRunner
from tensordict import TensorDict

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import MLP_VIEW
from navi_env.ecosystem.gym import NaviVectorEnv, make_vector_env
from navi_env.ecosystem.rsl_rl import OBS_GROUPS, RslRlEnv
from navi_learner.evaluation.baselines import EvalPolicy

HIDDEN = 128
ROLLOUT = 32


def runner_config(recurrent: bool) -> dict:
    """OnPolicyRunner's configuration: rsl_rl's PPO defaults, MLP (or GRU + MLP) actor and critic."""
    model = {"hidden_dims": [HIDDEN, HIDDEN], "activation": "elu", "obs_normalization": True}
    if recurrent:
        model |= {"class_name": "RNNModel", "rnn_type": "gru", "rnn_hidden_dim": HIDDEN, "rnn_num_layers": 1}
    else:
        model |= {"class_name": "MLPModel"}
    gaussian = {"class_name": "GaussianDistribution", "init_std": 1.0, "std_type": "scalar"}
    return {
        "num_steps_per_env": ROLLOUT,
        "save_interval": 10**9,
        "obs_groups": dict(OBS_GROUPS),
        "algorithm": {"class_name": "PPO"},
        "actor": model | {"distribution_cfg": gaussian},
        "critic": dict(model),
    }


def snapshot(actor: MLPModel) -> MLPModel:
    """A copy of the actor (weights, normaliser) without the live state of the rollout: its last action
    distribution and, for a recurrent actor, its hidden state (the runner keeps using both)."""
    rnn = getattr(actor, "rnn", None)
    held = (actor.distribution._distribution, rnn.hidden_state if rnn is not None else None)
    actor.distribution._distribution = None
    if rnn is not None:
        rnn.hidden_state = None
    try:
        return copy.deepcopy(actor)
    finally:
        actor.distribution._distribution = held[0]
        if rnn is not None:
            rnn.hidden_state = held[1]


class MeanActor:
    """An EvalPolicy over a copy of the trained actor: its mean action on the pooled view, its GRU state
    (with --recurrent) zeroed for every actor whose episode restarted."""

    def __init__(self, name: str, actor: MLPModel, env: RslRlEnv) -> None:
        self.name = name
        self.actor = snapshot(actor).eval()
        self.env = env

    def reset(self, n: int, device: torch.device) -> None:
        self.actor.reset()  # no hidden state: the first step starts from zeros

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        groups: TensorDict = self.env.observations(obs)  # "policy", "critic": (N, 3·16·4)
        with torch.inference_mode():
            self.actor.reset(resets.long())  # (N,) 1 where a new episode began
            return self.actor(groups).clamp(-1.0, 1.0)  # (N, 4) the mean action


class RslRlLearner:
    """rsl_rl's OnPolicyRunner over RslRlEnv (the example's Learner)."""

    rollout = ROLLOUT

    def __init__(
        self,
        corpus: str,
        actors: int,
        config: EnvConfig,
        device: str = "cpu",
        seed: int = 0,
        recurrent: bool = False,
    ) -> None:
        torch.manual_seed(seed)
        vector = make_vector_env(actors, corpus, device, config)
        assert isinstance(vector, NaviVectorEnv)
        self.env = RslRlEnv(vector, seed=seed, view=MLP_VIEW)  # groups (N, 3·16·4), the pooled view
        self.runner = OnPolicyRunner(self.env, runner_config(recurrent), log_dir=None, device=device)
        core = f"GRU {HIDDEN} + " if recurrent else ""
        inputs = self.env.obs["policy"].shape[1]
        self.name = "rsl_rl PPO" + (" (GRU)" if recurrent else "")
        self.encoder = f"{core}MLP {HIDDEN}-{HIDDEN} over the pooled {MLP_VIEW[0]} x {MLP_VIEW[1]} view ({inputs} inputs)"
        self.started = False

    def learn(self, steps: int) -> None:
        self.runner.learn(math.ceil(steps / ROLLOUT), init_at_random_ep_len=not self.started)
        self.started = True

    def policy(self) -> EvalPolicy:
        return MeanActor(self.name, self.runner.alg.get_policy(), self.env)


def train(
    corpus: str,
    actors: int,
    steps: int,
    config: EnvConfig,
    device: str = "cpu",
    seed: int = 0,
    recurrent: bool = False,
) -> EvalPolicy:
    """PPO for `steps` steps of `actors` drones; returns the trained policy's mean action."""
    learner = RslRlLearner(corpus, actors, config, device, seed, recurrent)
    learner.learn(steps)
    return learner.policy()


def make(
    corpus: str, actors: int, config: EnvConfig, device: str = "cpu", seed: int = 0, recurrent: bool = False
) -> Learner:
    return RslRlLearner(corpus, actors, config, device, seed, recurrent)


if __name__ == "__main__":
    main(__doc__, make, flags=(("--recurrent", "a GRU in front of the actor's and the critic's MLP"),))
