"""Evaluation: run a policy (a checkpoint, a live engine, random, reactive) against a BatchedEnv and
summarise it with 95% bootstrap confidence intervals over actors.

Every policy sees the same env seed, so the same scenes and spawns. Metrics (each a ratio of per-actor
sums, so the bootstrap resamples actors and recomputes the ratio):
  episode_return     mean return of the episodes that finished during the evaluation (NaN if none did)
  reward_per_step    extrinsic reward per actor-step
  collisions_per_1k  contact steps per 1,000 actor-steps
  obstacle_collisions_per_1k  of those, contacts with moving obstacles (0 without; NaN if the env has none)
  mean_clearance     the env's clearance (info["clearance"]) per actor-step
  coverage_per_1k    distinct 1 m cells visited per actor-episode, per 1,000 actor-steps
  distance_per_1k    meters flown per 1,000 actor-steps
  starvation_rate    starved episodes / finished episodes
Point-goal episodes (an env whose info has "success"; docs/TASKS.md), over the episodes that finished:
  success_rate       episodes that ended at the goal / finished episodes
  spl                success weighted by path length: S * l / max(p, l), l the shortest path length from
                     the start, p the meters flown (Anderson et al. 2018)
  soft_spl           max(0, 1 - d_T / l) * l / max(p, l), d_T the path length left at the end
  collisions_per_episode  contact steps / finished episodes
  time_to_goal_s     seconds of simulated time per successful episode
Info keys that an env lacks give NaN for that metric.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from navi_learner.config import EngineConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState
from navi_learner.envs.protocol import BatchedEnv, StepLike, capabilities
from navi_learner.evaluation.baselines import EvalPolicy
from navi_learner.serving.checkpoint import load_checkpoint

METRICS: tuple[str, ...] = (
    "episode_return",
    "reward_per_step",
    "collisions_per_1k",
    "obstacle_collisions_per_1k",
    "mean_clearance",
    "coverage_per_1k",
    "distance_per_1k",
    "starvation_rate",
    "success_rate",
    "spl",
    "soft_spl",
    "collisions_per_episode",
    "time_to_goal_s",
)
"""The metrics of an evaluation, each with a confidence interval."""

BOOTSTRAP_SAMPLES = 1000
"""Resamples of the actors behind every confidence interval."""

PAIRED_SUMS = ("steps", "cells", "collision")
"""The per-actor sums an evaluation keeps for paired comparisons of two policies flown on the same seed."""

ACTION_NOISE: dict[str, float] = {"explore": 1.0, "pointgoal": 0.0}
"""How a trained policy flies each task wherever Navi evaluates it (the main job, the benchmarks, `navi
evaluate`): its actions sampled with this many times its learned std, or at 0 its mean action. Explore
samples, as it trained: flown on its mean action a drone pressed against a surface sees the same view and
pushes again, and on real maps never seen it collides several times as often (docs/TRAINING.md, "Sampled
actions"). Point-goal flies its mean action: sampled, it reaches fewer goals by longer paths."""


def action_noise(task: str) -> float:
    """ACTION_NOISE of a task; ValueError for an unknown one."""
    if task not in ACTION_NOISE:
        raise ValueError(f"unknown task {task!r}: expected one of {', '.join(ACTION_NOISE)}")
    return ACTION_NOISE[task]


def flown_by(task: str) -> str:
    """How a trained policy of `task` flies, in words for reports."""
    noise = action_noise(task)
    if noise == 0:
        return "the trained policy's mean actions"
    return "the trained policy's actions sampled with " + (
        "its learned std" if noise == 1 else f"{noise:g} times its learned std"
    )


COLLISION_FLOOR_PER_1K = 0.5
"""Collisions per 1,000 steps below which two policies count as equally safe: the competence bar where
the reactive baseline has no collisions at all (half of none would demand none)."""


class ModulePolicy:
    """A CognitiveMambaPolicy (live or loaded) driven step by step with its recurrent state; its mean action
    at noise 0, else its actions sampled with `noise` times its learned std from a stream of its own
    (seeded by `seed` at every reset, so an evaluation flies the same draws each time)."""

    def __init__(self, policy: CognitiveMambaPolicy, name: str, noise: float = 0.0, seed: int = 0) -> None:
        if noise < 0:
            raise ValueError(f"action noise must be >= 0, got {noise}")
        self.policy = policy
        self.name = name
        self.noise = noise
        self.seed = seed
        self.state: CoreState = ()
        self.generator: torch.Generator | None = None
        # (4,) float64 per action axis: the actor-steps since the last reset whose mean lay beyond ±1
        self.outside: torch.Tensor | None = None
        self.steps = 0  # actor-steps since the last reset

    def reset(self, n: int, device: torch.device) -> None:
        self.state = self.policy.initial_state(n, device)
        self.generator = torch.Generator(device).manual_seed(self.seed) if self.noise > 0 else None
        self.outside = torch.zeros(4, dtype=torch.float64, device=device)  # (4,)
        self.steps = 0

    def act(self, obs: torch.Tensor, resets: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            out = self.policy.act(obs, resets, self.state, self.noise == 0, self.noise, self.generator)
        self.state = out.state
        if self.outside is not None:
            self.outside += (out.mean.abs() > 1.0).sum(dim=0)  # (4,)
            self.steps += out.mean.shape[0]
        return out.action.clamp(-1.0, 1.0)  # (N, 4)

    def mean_outside(self) -> list[float]:
        """Per action axis [forward, vertical, lateral, yaw_rate], the share of the actor-steps since the last
        reset whose action mean lay outside [-1, 1], the box the env clips every action to (one host read)."""
        if self.outside is None or self.steps == 0:
            return [math.nan] * 4
        return (self.outside / self.steps).tolist()


class CheckpointPolicy(ModulePolicy):
    """A trained checkpoint (no PPO, no reward shaping), flown with `noise` (None: ACTION_NOISE of the task
    it learned)."""

    def __init__(self, path: Path, device: torch.device, noise: float | None = None, seed: int = 0) -> None:
        ckpt = load_checkpoint(path, device)
        shape = ckpt.meta.obs_shape
        self.obs_shape = (int(shape[0]), int(shape[1]), int(shape[2]))
        policy = CognitiveMambaPolicy(self.obs_shape, EngineConfig.from_dict(ckpt.meta.config["engine"])).to(
            device
        )
        policy.load_state_dict(ckpt.model)
        policy.eval()
        task = str(ckpt.meta.config.get("task", "explore"))
        super().__init__(policy, str(path), action_noise(task) if noise is None else noise, seed)


@dataclass
class EvalMetrics:
    """Result of one evaluation (JSON-friendly); `ci` maps every metric to its [low, high] 95% interval."""

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
    obstacle_collisions_per_1k: float = math.nan  # results saved before moving obstacles lack it
    success_rate: float = math.nan  # point-goal metrics: NaN for exploration
    spl: float = math.nan
    soft_spl: float = math.nan
    collisions_per_episode: float = math.nan
    time_to_goal_s: float = math.nan
    task: str = "explore"  # pointgoal when the env reported point-goal episodes
    ci: dict[str, list[float]] = field(default_factory=dict)
    mean_outside: list[float] = field(default_factory=list)
    """A trained policy's share of actor-steps whose action mean lay outside [-1, 1], where the env clips,
    per axis [forward, vertical, lateral, yaw_rate] (ModulePolicy.mean_outside); empty for the baselines."""
    per_actor: dict[str, list[float]] = field(default_factory=dict)
    """Per-actor sums behind the paired comparisons (PAIRED_SUMS: steps, cells, collision), (N,) each."""
    per_scene: dict[str, dict[str, float]] = field(default_factory=dict)
    """With `evaluate(by_scene=True)`: scene name -> its actors' count ("actors") and every metric's point
    value over them (no intervals), each actor counted in the scene it flew first."""


@dataclass
class ActorSums:
    """Per-actor sums of one evaluation, (N,) float64 each; every metric is a ratio of two of them."""

    steps: np.ndarray
    reward: np.ndarray
    finished_return: np.ndarray
    episodes: np.ndarray
    collision: np.ndarray
    obstacle_collision: np.ndarray
    clearance: np.ndarray
    starved: np.ndarray
    distance: np.ndarray
    cells: np.ndarray
    success: np.ndarray
    spl: np.ndarray
    soft_spl: np.ndarray
    goal_seconds: np.ndarray

    def ratios(self) -> dict[str, tuple[np.ndarray, np.ndarray, float]]:
        """metric -> (numerator (N,), denominator (N,), scale)."""
        return {
            "episode_return": (self.finished_return, self.episodes, 1.0),
            "reward_per_step": (self.reward, self.steps, 1.0),
            "collisions_per_1k": (self.collision, self.steps, 1000.0),
            "obstacle_collisions_per_1k": (self.obstacle_collision, self.steps, 1000.0),
            "mean_clearance": (self.clearance, self.steps, 1.0),
            "coverage_per_1k": (self.cells, self.steps, 1000.0),
            "distance_per_1k": (self.distance, self.steps, 1000.0),
            "starvation_rate": (self.starved, self.episodes, 1.0),
            "success_rate": (self.success, self.episodes, 1.0),
            "spl": (self.spl, self.episodes, 1.0),
            "soft_spl": (self.soft_spl, self.episodes, 1.0),
            "collisions_per_episode": (self.collision, self.episodes, 1.0),
            "time_to_goal_s": (self.goal_seconds, self.success, 1.0),
        }


NEEDS = {
    "collisions_per_1k": "collision",
    "obstacle_collisions_per_1k": "obstacle_collision",
    "mean_clearance": "clearance",
    "coverage_per_1k": "position",
    "distance_per_1k": "position",
    "starvation_rate": "starved",
    "success_rate": "success",
    "spl": "success",
    "soft_spl": "success",
    "collisions_per_episode": "success",
    "time_to_goal_s": "success",
}
"""The info key each metric needs (an env without it gives NaN)."""


def ratio(num: np.ndarray, den: np.ndarray, scale: float) -> float:
    """scale * sum(num) / sum(den), NaN when the denominator is 0."""
    total = float(den.sum())
    return scale * float(num.sum()) / total if total > 0 else math.nan


def bootstrap_ci(
    num: np.ndarray, den: np.ndarray, scale: float, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0
) -> list[float]:
    """95% percentile interval of the ratio over `samples` resamples of the actors (with replacement)."""
    n = num.shape[0]
    idx = np.random.default_rng(seed).integers(0, n, size=(samples, n))  # (B, N)
    nums, dens = num[idx].sum(axis=1), den[idx].sum(axis=1)  # (B,) each
    ok = dens > 0
    if not ok.any():
        return [math.nan, math.nan]
    values = scale * nums[ok] / dens[ok]  # (B',)
    return [float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5))]


def summarise(name: str, sums: ActorSums, steps: int, has: dict[str, bool], elapsed: float) -> EvalMetrics:
    """EvalMetrics with bootstrap intervals from per-actor sums; metrics without their info key are NaN."""
    values: dict[str, Any] = {}  # metric name -> float, unpacked into EvalMetrics
    ci: dict[str, list[float]] = {}
    for metric, (num, den, scale) in sums.ratios().items():
        if not has.get(NEEDS.get(metric, ""), True):
            values[metric], ci[metric] = math.nan, [math.nan, math.nan]
            continue
        values[metric] = ratio(num, den, scale)
        ci[metric] = bootstrap_ci(num, den, scale)
    n = sums.steps.shape[0]
    per_actor = {k: getattr(sums, k).tolist() for k in PAIRED_SUMS}
    return EvalMetrics(
        policy=name,
        steps=steps,
        actors=n,
        episodes=int(sums.episodes.sum()),
        task="pointgoal" if has.get("success", False) else "explore",
        sps=n * steps / max(elapsed, 1e-9),
        ci=ci,
        per_actor=per_actor,
        per_scene={},
        **values,
    )


def scene_values(
    sums: ActorSums, scene: np.ndarray, names: Sequence[str], has: dict[str, bool]
) -> dict[str, dict[str, float]]:
    """Per scene name: its actors' count and the point value of every metric over them; actors (N,) are
    grouped by `scene` (N,) int64, the index into `names`. Metrics without their info key are NaN."""
    out: dict[str, dict[str, float]] = {}
    for k, name in enumerate(names):
        mine = scene == k  # (N,) bool
        if not mine.any():
            continue
        row: dict[str, float] = {"actors": float(mine.sum())}
        for metric, (num, den, scale) in sums.ratios().items():
            known = has.get(NEEDS.get(metric, ""), True)
            row[metric] = ratio(num[mine], den[mine], scale) if known else math.nan
        out[name] = row
    return out


Observer = Callable[[StepLike, torch.Tensor], None]
"""What `evaluate` calls after every step with its output and the actions that made it."""


def evaluate(
    env: BatchedEnv,
    policy: EvalPolicy,
    steps: int,
    seed: int = 0,
    progress: bool = False,
    by_scene: bool = False,
    observe: Observer | None = None,
) -> EvalMetrics:
    """Run `steps` batched steps from env.reset(seed) and summarise (one host read at the end). With
    `by_scene` the result also holds per-scene values (EvalMetrics.per_scene; the env's info "scene_id"
    and its capabilities' scene names); `observe` sees every step's output and the actions (N, 4) that made
    it (analyses that record more)."""
    n, device = env.n_actors, env.device
    policy.reset(n, device)
    obs = env.reset(seed=seed)
    resets = torch.ones(n, dtype=torch.bool, device=device)  # (N,)
    names = (
        "reward",
        "finished_return",
        "episodes",
        "collision",
        "obstacle_collision",
        "clearance",
        "starved",
        "distance",
        "success",
        "spl",
        "soft_spl",
        "goal_seconds",
    )
    dt = capabilities(env).dt  # seconds per step
    acc = {k: torch.zeros(n, dtype=torch.float64, device=device) for k in names}  # (N,) float64 each
    has = {
        k: False for k in ("collision", "obstacle_collision", "clearance", "starved", "position", "success")
    }
    ret = torch.zeros(n, dtype=torch.float64, device=device)  # (N,) return of the running episode
    episode = torch.zeros(n, dtype=torch.long, device=device)  # (N,) episode index per actor
    ids = torch.arange(n, device=device)  # (N,)
    cells: list[torch.Tensor] = []
    prev_pos: torch.Tensor | None = None
    same_episode = torch.zeros(n, dtype=torch.bool, device=device)  # (N,) prev_pos is this episode's
    first_scene: torch.Tensor | None = None  # (N,) int64 the scene each actor flew first
    t0 = time.perf_counter()
    for i in range(steps):
        action = policy.act(obs, resets)  # (N, 4)
        out = env.step(action)
        if observe is not None:
            observe(out, action)
        if by_scene and first_scene is None:
            if "scene_id" not in out.info:
                raise ValueError("by_scene needs an env whose info has scene_id (the drone env)")
            first_scene = out.info["scene_id"].long().clone()
        ends = out.done | out.truncated  # (N,) bool
        ret += out.reward
        acc["reward"] += out.reward
        acc["finished_return"] += ret * ends
        acc["episodes"] += ends
        for key in ("collision", "obstacle_collision", "clearance", "starved"):
            if key in out.info:
                has[key] = True
                acc[key] += out.info[key].double()
        if "success" in out.info:  # point-goal: score the episodes that ended here
            has["success"] = True
            success = out.info["success"].double()  # (N,) 1 where the episode ended at the goal
            shortest = out.info["start_distance"].double()  # (N,)
            efficiency = shortest / torch.maximum(out.info["path_length"].double(), shortest).clamp(min=1e-9)
            gained = (1.0 - out.info["goal_distance"].double() / shortest.clamp(min=1e-9)).clamp(min=0.0)
            acc["success"] += success
            acc["spl"] += success * efficiency
            acc["soft_spl"] += ends * gained * efficiency
            acc["goal_seconds"] += success * out.info["episode_length"].double() * dt
        if "position" in out.info:
            has["position"] = True
            pos = out.info["position"].float().clone()  # (N, 3) after this step's move, before any reset
            if prev_pos is not None:
                acc["distance"] += (pos - prev_pos).norm(dim=1).double() * same_episode
            cells.append(
                torch.cat([ids[:, None], episode[:, None], torch.floor(pos).long()], dim=1)
            )  # (N, 5)
            prev_pos = pos
            same_episode = ~ends
        ret *= ~ends
        episode += ends.long()
        obs, resets = out.obs, ends
        if progress and sys.stderr.isatty() and i % 50 == 0:
            sys.stderr.write(f"\r{policy.name}: {i}/{steps} steps")
    covered = torch.zeros(n, dtype=torch.float64, device=device)  # (N,)
    if cells:
        visited = torch.unique(torch.cat(cells), dim=0)  # (V, 5) distinct (actor, episode, cell)
        covered = torch.bincount(visited[:, 0], minlength=n).double()
    host = {k: v.cpu().numpy() for k, v in acc.items()}
    elapsed = time.perf_counter() - t0
    if progress and sys.stderr.isatty():
        sys.stderr.write("\n")
    sums = ActorSums(steps=np.full(n, float(steps)), cells=covered.cpu().numpy(), **host)
    result = summarise(policy.name, sums, steps, has, elapsed)
    if first_scene is not None:
        result.per_scene = scene_values(sums, first_scene.cpu().numpy(), capabilities(env).scenes, has)
    if isinstance(policy, ModulePolicy):
        result.mean_outside = policy.mean_outside()
    return result


def observers(*each: Observer | None) -> Observer | None:
    """One `evaluate` observer calling each given one in turn (None where none is given)."""
    chosen = [o for o in each if o is not None]
    if not chosen:
        return None

    def call(out: StepLike, action: torch.Tensor) -> None:
        for o in chosen:
            o(out, action)

    return call


def scene_table(
    rows: Mapping[str, Mapping[str, Any]], columns: Sequence[str], cell: Callable[[str, Any], str]
) -> str:
    """A markdown table of per-scene rows (scene name -> column -> value): one line per scene by name, then
    "all"; `cell(column, value)` writes a cell."""
    lines = ["| scene | " + " | ".join(columns) + " |", "| --- |" + " --- |" * len(columns)]
    for name in [*sorted(k for k in rows if k != "all"), "all"]:
        if name in rows:
            lines.append(f"| {name} | " + " | ".join(cell(k, rows[name].get(k)) for k in columns) + " |")
    return "\n".join(lines)


def jsonable(value: object) -> object:
    """Plain JSON values: NaN becomes None, recursively through dicts, lists and dataclass dicts."""
    if isinstance(value, float):
        return None if math.isnan(value) else value
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    return value


def collision_bar(reactive: EvalMetrics, collisions: float = 0.5) -> float:
    """The most collisions per 1,000 steps the bar allows: `collisions` x the reactive baseline's, or
    COLLISION_FLOOR_PER_1K where the baseline has none."""
    if reactive.collisions_per_1k > 0:
        return collisions * reactive.collisions_per_1k
    return COLLISION_FLOOR_PER_1K


def competent(
    trained: EvalMetrics, reactive: EvalMetrics, collisions: float = 0.5, coverage: float = 1.5
) -> bool:
    """The competence bar of `navi bench learn`, on point estimates: collisions per 1,000 steps within
    collision_bar (half the reactive baseline's, COLLISION_FLOOR_PER_1K where it has none) and at least
    `coverage` x its coverage, on the same unseen scenes and seed."""
    return (
        trained.collisions_per_1k <= collision_bar(reactive, collisions)
        and trained.coverage_per_1k >= coverage * reactive.coverage_per_1k
    )


def paired_intervals(
    a: EvalMetrics, b: EvalMetrics, samples: int = BOOTSTRAP_SAMPLES, seed: int = 0
) -> dict[str, list[float]]:
    """95% intervals of a against b over the same resamples of the actors (both flown from the same env
    seed, so actor i starts from the same spawn in both): `coverage_ratio` (a's coverage per 1,000 steps
    over b's) and `collision_difference` (a's collisions per 1,000 steps minus b's). Pairing removes the
    spread between scenes that both policies share, which dominates each one's own interval."""
    for m in (a, b):
        if not all(k in m.per_actor for k in PAIRED_SUMS):
            raise ValueError(f"{m.policy}: no per-actor sums (an evaluation saved before they were kept)")
    if a.actors != b.actors or a.steps != b.steps:
        raise ValueError(f"{a.policy} and {b.policy} were not flown with the same actors and steps")
    sa = {k: np.asarray(a.per_actor[k]) for k in PAIRED_SUMS}  # (N,) each
    sb = {k: np.asarray(b.per_actor[k]) for k in PAIRED_SUMS}  # (N,) each
    idx = np.random.default_rng(seed).integers(0, a.actors, size=(samples, a.actors))  # (B, N)
    steps_a, steps_b = sa["steps"][idx].sum(axis=1), sb["steps"][idx].sum(axis=1)  # (B,) each
    cover_b = sb["cells"][idx].sum(axis=1) / steps_b  # (B,)
    ok = cover_b > 0
    ratio = (sa["cells"][idx].sum(axis=1) / steps_a)[ok] / cover_b[ok]  # (B',)
    diff = 1000.0 * (sa["collision"][idx].sum(axis=1) / steps_a - sb["collision"][idx].sum(axis=1) / steps_b)
    return {
        "coverage_ratio": [float(np.percentile(ratio, 2.5)), float(np.percentile(ratio, 97.5))]
        if ok.any()
        else [math.nan, math.nan],
        "collision_difference": [float(np.percentile(diff, 2.5)), float(np.percentile(diff, 97.5))],
    }


def beats_supported(trained: EvalMetrics, other: EvalMetrics) -> bool:
    """trained beats other with the intervals behind it: its coverage ratio's paired interval lies above
    1, and its extra collisions per 1,000 steps (paired interval's top) stay within COLLISION_FLOOR_PER_1K."""
    paired = paired_intervals(trained, other)
    return paired["coverage_ratio"][0] > 1.0 and paired["collision_difference"][1] <= COLLISION_FLOOR_PER_1K


def competent_supported(
    trained: EvalMetrics, reactive: EvalMetrics, collisions: float = 0.5, coverage: float = 1.5
) -> bool:
    """The competence bar held by the intervals, not only the point estimates: trained's collision
    interval lies within collision_bar, and the paired interval of its coverage ratio to the reactive
    baseline lies at or above `coverage`."""
    paired = paired_intervals(trained, reactive)
    return (
        trained.ci["collisions_per_1k"][1] <= collision_bar(reactive, collisions)
        and paired["coverage_ratio"][0] >= coverage
    )


def goal_competent(
    trained: EvalMetrics, greedy: EvalMetrics, success: float = 0.9, spl: float = 0.75
) -> bool:
    """The point-goal bar of `navi bench learn --task pointgoal`: a success rate of at least `success`,
    SPL of at least `spl`, and fewer collisions per episode than the map-less greedy baseline (no more,
    where that has none), on the same unseen scenes and seed."""
    fewer = trained.collisions_per_episode < greedy.collisions_per_episode or (
        greedy.collisions_per_episode == 0.0 and trained.collisions_per_episode == 0.0
    )
    return trained.success_rate >= success and trained.spl >= spl and fewer


def mean_outside_line(m: EvalMetrics) -> str:
    """The line printed under an evaluation's table for a trained policy: its `mean_outside` shares per
    action axis; "" for a policy without action means (the baselines)."""
    if not m.mean_outside:
        return ""
    shares = " / ".join(f"{x:.1%}" for x in m.mean_outside)
    return f"Action means outside [-1, 1], forward / vertical / lateral / yaw rate ({m.policy}): {shares}"


def contact_spread(per_actor: dict[str, list[float]], busiest: int = 3) -> dict[str, int] | None:
    """How an evaluation's contact steps spread over its actors (EvalMetrics.per_actor): the actors, those
    with any contact, all contact steps, those of the `busiest` actors, and the most of one actor; None
    where the evaluation kept no per-actor counts. Near the explore bar a few drones that keep touching
    make most of the count (docs/TRAINING.md, "Learning", lessons)."""
    counts = sorted(per_actor.get("collision", []), reverse=True)  # (N,) contact steps per actor
    if not counts:
        return None
    return {
        "actors": len(counts),
        "actors_in_contact": sum(c > 0 for c in counts),
        "contact_steps": round(sum(counts)),
        "busiest_steps": round(sum(counts[:busiest])),
        "most": round(counts[0]),
    }


def contact_line(m: EvalMetrics, who: str = "trained") -> str:
    """The line printed under an evaluation's table for a trained policy that touched anything: how few of
    its actors made the contact steps (contact_spread); "" without per-actor counts or contacts."""
    spread = contact_spread(m.per_actor)
    if not spread or not spread["contact_steps"]:
        return ""
    return (
        f"Contacts ({who}): {spread['actors_in_contact']} of {spread['actors']} actors touched a surface; "
        f"the 3 busiest made {spread['busiest_steps']} of the {spread['contact_steps']} contact steps "
        f"(one actor {spread['most']})."
    )


def comparison_table(rows: list[EvalMetrics]) -> str:
    """A markdown table of several evaluations: each metric with its 95% interval (the point-goal
    metrics when the evaluations have them)."""
    keys = ["collisions_per_1k", "coverage_per_1k", "episode_return", "reward_per_step", "mean_clearance"]
    keys += ["distance_per_1k", "starvation_rate"]
    if any(r.task == "pointgoal" for r in rows):
        keys = ["success_rate", "spl", "soft_spl", "collisions_per_episode", "time_to_goal_s"]
        keys += ["collisions_per_1k", "episode_return"]
    lines = ["| policy | " + " | ".join(keys) + " | episodes |", "| --- " * (len(keys) + 2) + "|"]
    for r in rows:
        cells = [
            f"{getattr(r, k):.4g} [{r.ci[k][0]:.3g}, {r.ci[k][1]:.3g}]"
            if k in r.ci
            else f"{getattr(r, k):.4g}"
            for k in keys
        ]
        lines.append(f"| {r.policy} | " + " | ".join(cells) + f" | {r.episodes} |")
    return "\n".join(lines)
