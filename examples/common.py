"""What the training examples share: their command line (`parser`, `env_config`), the interface every
example's trainer offers (`Learner`: learn for some steps, then fly the mean action) and their verdict
(`against_baselines`): Navi's own evaluation, `navi_learner.evaluation.evaluate`, flies the trained drone,
the random pilot and the scripted reactive avoider from the same spawns (same env seed) and reports
collisions and coverage per 1,000 steps with 95% intervals.

Every trainer reads the view through its adapter's pooling (navi_env.ecosystem.batch.pool_view, 16 x 4
by default) and normalises it with its library's own running normaliser: depth / horizon is about 0.01
a meter from a wall, beside a semantic channel of 0.5 on every hit."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple, Protocol

import torch

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import make_batched_env
from navi_learner.evaluation.baselines import EvalPolicy, RandomPolicy, reactive_for_env
from navi_learner.evaluation.evaluate import EvalMetrics, comparison_table, evaluate

EVAL_ACTORS, EVAL_STEPS, EVAL_SEED = 64, 400, 11
"""The verdict's evaluation: 64 drones for 400 steps from env seed 11."""


class Learner(Protocol):
    """A stock trainer over one of Navi's adapters, as the examples build it."""

    name: str
    """The trainer, e.g. "skrl PPO"."""
    encoder: str
    """What the policy reads, e.g. "MLP 128-128 over the pooled 16 x 4 view (192 inputs)"."""
    rollout: int
    """Steps per actor between two updates: learn() trains whole rollouts."""

    def learn(self, steps: int) -> None:
        """Train for `steps` more steps of every actor (whole rollouts, rounded up)."""
        ...

    def policy(self) -> EvalPolicy:
        """The trained policy's mean action as an EvalPolicy over the env's own observations."""
        ...


class MeanAction:
    """An EvalPolicy from `act`: obs (N, 3, Az, El) -> the policy's mean action (N, 4)."""

    def __init__(self, name: str, act: Callable[[torch.Tensor], torch.Tensor]) -> None:
        self.name = name
        self.forward = act

    def reset(self, n: int, device: torch.device) -> None:
        return None

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.forward(obs).clamp(-1.0, 1.0)  # (N, 4)


class Verdict(NamedTuple):
    """One evaluation of the trained policy and the two baselines, same spawns."""

    trained: EvalMetrics
    random: EvalMetrics
    reactive: EvalMetrics


def baselines(
    corpus: str | Path,
    config: EnvConfig,
    device: str = "cpu",
    actors: int = EVAL_ACTORS,
    steps: int = EVAL_STEPS,
    seed: int = EVAL_SEED,
) -> tuple[EvalMetrics, EvalMetrics]:
    """(random, reactive) on `actors` drones of the corpus for `steps` steps from env seed `seed`."""
    env = make_batched_env(corpus, actors, device, config, seed=seed)
    rand = evaluate(env, RandomPolicy(seed), steps, seed=seed)
    return rand, evaluate(env, reactive_for_env(env), steps, seed=seed)


def fly(
    corpus: str | Path,
    policy: EvalPolicy,
    config: EnvConfig,
    device: str = "cpu",
    actors: int = EVAL_ACTORS,
    steps: int = EVAL_STEPS,
    seed: int = EVAL_SEED,
) -> EvalMetrics:
    """The policy's evaluation on the same spawns as `baselines` with the same arguments."""
    return evaluate(make_batched_env(corpus, actors, device, config, seed=seed), policy, steps, seed=seed)


def against_baselines(
    corpus: str | Path, policy: EvalPolicy, config: EnvConfig, device: str = "cpu", **protocol: int
) -> Verdict:
    """(trained, random, reactive) from the same spawns (`protocol`: actors, steps, seed); prints the table."""
    trained = fly(corpus, policy, config, device, **protocol)
    verdict = Verdict(trained, *baselines(corpus, config, device, **protocol))
    print(comparison_table(list(verdict)))
    return verdict


def parser(doc: str | None, steps: int) -> argparse.ArgumentParser:
    """The examples' command line: --corpus, --unseen, --actors, --steps, --device, --full-view, --seed."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--corpus", required=True, help="a corpus folder (navi corpus build) to train on")
    p.add_argument(
        "--unseen",
        default=None,
        help="a corpus folder of scenes the drone never trained on, where the verdict is flown "
        "(default: the training corpus)",
    )
    p.add_argument("--actors", type=int, default=64, help="drones flown together")
    p.add_argument("--steps", type=int, default=steps, help="training budget: steps of every drone")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--full-view", action="store_true", help="trace 256 x 48 rays instead of 16 x 4")
    p.add_argument("--seed", type=int, default=0, help="seed of the networks and the training env")
    return p


def env_config(args: argparse.Namespace) -> EnvConfig:
    """The EnvConfig the command line asks for: 16 x 4 rays (fast on a CPU) unless --full-view (256 x 48,
    which the adapters pool to the same 16 x 4 view for the MLP: every ray is traced, the nearest of each
    block is kept)."""
    return EnvConfig() if args.full_view else EnvConfig(azimuth_bins=16, elevation_bins=4)


def main(
    doc: str | None,
    make: Callable[..., Learner],
    steps: int = 3072,
    flags: tuple[tuple[str, str], ...] = (),
    argv: list[str] | None = None,
) -> Verdict:
    """An example's command (`argv`, default sys.argv): build its Learner from the command line (and its
    own boolean `flags`, (option, help) pairs passed to `make` by name), train it, print the verdict on
    the --unseen corpus (the training corpus without it)."""
    p = parser(doc, steps)
    for option, text in flags:
        p.add_argument(option, action="store_true", help=text)
    args = p.parse_args(argv)
    config = env_config(args)
    extra = {option.removeprefix("--").replace("-", "_"): True for option, _ in flags}
    extra = {name: getattr(args, name) for name in extra}
    learner = make(args.corpus, args.actors, config, args.device, args.seed, **extra)
    learner.learn(args.steps)
    return against_baselines(args.unseen or args.corpus, learner.policy(), config, args.device)
