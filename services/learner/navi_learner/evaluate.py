"""Evaluation: run a policy (checkpoint, random, reactive) against a BatchedEnv and compute metrics.

Every policy sees the same env seed, so the same scenes and spawns. Metrics: episode return,
reward per step, collisions per 1,000 steps, mean clearance, coverage (distinct 1 m cells visited
per actor-episode, per 1,000 steps), distance flown per 1,000 steps, starvation rate (starved
episodes / finished episodes). Info keys that an env lacks give NaN for that metric.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from navi_learner.baselines import EvalPolicy
from navi_learner.checkpoint import load_checkpoint
from navi_learner.config import EngineConfig
from navi_learner.policy import CognitiveMambaPolicy
from navi_learner.protocol import BatchedEnv
from navi_learner.temporal import CoreState


class CheckpointPolicy:
    """A trained CognitiveMambaPolicy with its recurrent state (no PPO, no reward shaping)."""

    def __init__(self, path: Path, device: torch.device, deterministic: bool = True) -> None:
        ckpt = load_checkpoint(path, device)
        shape = ckpt.meta.obs_shape
        self.name = str(path)
        self.obs_shape = (int(shape[0]), int(shape[1]), int(shape[2]))
        self.policy = CognitiveMambaPolicy(self.obs_shape, EngineConfig(**ckpt.meta.config["engine"])).to(
            device
        )
        self.policy.load_state_dict(ckpt.model)
        self.policy.eval()
        self.deterministic = deterministic
        self.state: CoreState = ()

    def reset(self, n: int, device: torch.device) -> None:
        self.state = self.policy.initial_state(n, device)

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            out = self.policy.act(obs, resets, self.state, self.deterministic)
        self.state = out.state
        return out.action.clamp(-1.0, 1.0)  # (N, 4)


@dataclass
class EvalMetrics:
    """Result of one evaluation (JSON-friendly)."""

    policy: str
    steps: int
    actors: int
    episodes: int
    episode_return: float
    reward_per_step: float
    collisions_per_1k: float
    mean_clearance: float
    coverage_per_1k: float
    distance_per_1k: float
    starvation_rate: float
    sps: float


def evaluate(
    env: BatchedEnv, policy: EvalPolicy, steps: int, seed: int = 0, progress: bool = False
) -> EvalMetrics:
    """Run `steps` batched steps from env.reset(seed) and summarise (one host read at the end)."""
    n, device = env.n_actors, env.device
    policy.reset(n, device)
    obs = env.reset(seed=seed)
    resets = torch.ones(n, dtype=torch.bool, device=device)  # (N,)
    zero = torch.zeros((), device=device)  # ()
    ret, episode = torch.zeros(n, device=device), torch.zeros(n, dtype=torch.long, device=device)  # (N,) each
    sums = {
        k: zero.clone()
        for k in ("reward", "finished_return", "episodes", "collision", "clearance", "starved", "distance")
    }
    has = {k: False for k in ("collision", "clearance", "starved", "position")}
    cells: list[torch.Tensor] = []
    prev_pos: torch.Tensor | None = None
    moved_ok = torch.zeros(n, dtype=torch.bool, device=device)  # (N,) previous position is this episode's
    t0 = time.perf_counter()
    for i in range(steps):
        out = env.step(policy.act(obs, resets))
        ends = out.done | out.truncated  # (N,) bool
        ret += out.reward
        sums["reward"] += out.reward.sum()
        sums["finished_return"] += (ret * ends).sum()
        sums["episodes"] += ends.sum()
        for key in ("collision", "clearance", "starved"):
            if key in out.info:
                has[key] = True
                sums[key] += out.info[key].float().sum()
        if "position" in out.info:
            has["position"] = True
            pos = out.info["position"].float().clone()  # (N, 3)
            if prev_pos is not None:
                sums["distance"] += ((pos - prev_pos).norm(dim=1) * (moved_ok & ~ends)).sum()
            cell = torch.floor(pos).long()  # (N, 3)
            ids = torch.arange(n, device=device)  # (N,)
            cells.append(torch.cat([ids[:, None], episode[:, None], cell], dim=1))  # (N, 5) int64
            prev_pos = pos
            moved_ok = ~ends
        ret *= ~ends
        episode += ends.long()
        obs, resets = out.obs, ends
        if progress and sys.stderr.isatty() and i % 50 == 0:
            sys.stderr.write(f"\r{policy.name}: {i}/{steps} steps")
    total = n * steps
    host = {k: float(v) for k, v in sums.items()}
    elapsed = time.perf_counter() - t0
    if progress and sys.stderr.isatty():
        sys.stderr.write("\n")
    nan = float("nan")
    episodes = int(host["episodes"])
    coverage = nan
    if has["position"]:
        visited = torch.unique(torch.cat(cells), dim=0)  # (V, 5) distinct (actor, episode, cell)
        coverage = 1000.0 * visited.shape[0] / total
    return EvalMetrics(
        policy=policy.name,
        steps=steps,
        actors=n,
        episodes=episodes,
        episode_return=host["finished_return"] / episodes if episodes else float((ret.sum() / n).item()),
        reward_per_step=host["reward"] / total,
        collisions_per_1k=1000.0 * host["collision"] / total if has["collision"] else nan,
        mean_clearance=host["clearance"] / total if has["clearance"] else nan,
        coverage_per_1k=coverage,
        distance_per_1k=1000.0 * host["distance"] / total if has["position"] else nan,
        starvation_rate=host["starved"] / episodes if has["starved"] and episodes else nan,
        sps=total / max(elapsed, 1e-9),
    )


def comparison_table(rows: list[EvalMetrics]) -> str:
    """A markdown table of several evaluations."""
    keys = [
        "episode_return",
        "reward_per_step",
        "collisions_per_1k",
        "mean_clearance",
        "coverage_per_1k",
        "distance_per_1k",
        "starvation_rate",
        "episodes",
    ]
    lines = ["| policy | " + " | ".join(keys) + " |", "| --- " * (len(keys) + 1) + "|"]
    for r in rows:
        lines.append(f"| {r.policy} | " + " | ".join(f"{getattr(r, k):.4g}" for k in keys) + " |")
    return "\n".join(lines)
