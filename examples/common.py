"""What the training examples share: their command line (`arguments`) and their verdict
(`against_random`): Navi's own evaluation, `navi_learner.evaluation.evaluate`, flies the trained drone
and the random pilot from the same spawns (same env seed) and reports collisions and coverage per 1,000
steps with 95% intervals."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import torch

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import make_batched_env
from navi_learner.evaluation.baselines import RandomPolicy
from navi_learner.evaluation.evaluate import EvalMetrics, comparison_table, evaluate


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


def against_random(
    corpus: str | Path,
    name: str,
    act: Callable[[torch.Tensor], torch.Tensor],
    config: EnvConfig,
    device: str = "cpu",
    actors: int = 64,
    steps: int = 400,
    seed: int = 11,
) -> tuple[EvalMetrics, EvalMetrics]:
    """(trained, random) on `actors` drones of the corpus for `steps` steps; prints the table."""
    runs = []
    for policy in (MeanAction(name, act), RandomPolicy(seed)):
        env = make_batched_env(corpus, actors, device, config, seed=seed)
        runs.append(evaluate(env, policy, steps, seed=seed))
    print(comparison_table(runs))
    return runs[0], runs[1]


def arguments(doc: str | None, steps: int) -> tuple[argparse.Namespace, EnvConfig]:
    """The examples' command line (--corpus, --actors, --steps, --device, --full-view) and the EnvConfig
    it asks for: 16 x 4 rays (fast on a CPU) unless --full-view (256 x 48)."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--corpus", required=True, help="a corpus folder (navi corpus build)")
    parser.add_argument("--actors", type=int, default=64, help="drones flown together")
    parser.add_argument("--steps", type=int, default=steps, help="training budget")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--full-view", action="store_true", help="256 x 48 rays instead of 16 x 4")
    args = parser.parse_args()
    return args, EnvConfig() if args.full_view else EnvConfig(azimuth_bins=16, elevation_bins=4)
