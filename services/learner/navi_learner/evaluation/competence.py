"""Learning measured on unseen scenes: the evaluation protocol, the competence bar, and a training
monitor that evaluates the live weights every so often (flown as a checkpoint of them is) and records
the learning curve.

Competence (docs/TRAINING.md): on the unseen scenes, with the same seed, the policy flown as its task is
(ACTION_NOISE), at most half the reactive baseline's collisions per 1,000 steps (0.5 where it has none)
and at least 1.5x its coverage. For point-goal episodes (docs/TASKS.md): a success rate of at least
0.9, SPL of at least 0.75 and fewer collisions per episode than the map-less greedy baseline.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.envs.protocol import BatchedEnv, capabilities
from navi_learner.evaluation.baselines import EvalPolicy, RandomPolicy, goal_seeker_for_env, reactive_for_env
from navi_learner.evaluation.evaluate import (
    EvalMetrics,
    ModulePolicy,
    action_noise,
    competent,
    competent_supported,
    evaluate,
    goal_competent,
)

CURVE_KEYS = (
    "collisions_per_1k",
    "obstacle_collisions_per_1k",
    "coverage_per_1k",
    "episode_return",
    "reward_per_step",
    "success_rate",
    "spl",
    "soft_spl",
    "collisions_per_episode",
)
"""The metrics each learning-curve point records (with their intervals; the point-goal ones are NaN for
exploration)."""


@dataclass(frozen=True)
class EvalProtocol:
    """How a policy is evaluated on unseen scenes: `actors` drones for `steps` steps from env seed
    `seed`, episodes of `episode_steps` steps (so `steps / episode_steps` episodes per actor finish and
    returns are those of finished episodes)."""

    actors: int = 256
    steps: int = 1000
    episode_steps: int = 500
    seed: int = 12345

    @classmethod
    def for_device(cls, device: torch.device, task: str = "explore") -> EvalProtocol:
        """256 actors x 1,000 steps on a GPU (512 episodes); on a CPU 48 actors x 500 steps, episodes of
        250 (96 episodes, about 75 s a policy on 2 cores): enough that the paired intervals of the main
        job's verdict separate a competent drone from the reactive baseline. Point-goal episodes keep
        their own time limit on a CPU too (POINTGOAL_EPISODE_STEPS: a goal 30 m away must be reachable
        within the episode): 48 actors x 1,000 steps, episodes of 500."""
        if device.type == "cuda":
            return cls()
        if task == "pointgoal":
            from navi_env.config import POINTGOAL_EPISODE_STEPS

            return cls(actors=48, steps=2 * POINTGOAL_EPISODE_STEPS, episode_steps=POINTGOAL_EPISODE_STEPS)
        return cls(actors=48, steps=500, episode_steps=250)


def baseline_policies(env: BatchedEnv, protocol: EvalProtocol) -> list[EvalPolicy]:
    """The task's baselines for `env`: random and reactive; random, greedy and oracle for point-goal episodes."""
    policies: list[EvalPolicy] = [RandomPolicy(protocol.seed)]
    if capabilities(env).task == "pointgoal":
        policies += [goal_seeker_for_env("greedy", env), goal_seeker_for_env("oracle", env)]
    else:
        policies.append(reactive_for_env(env))
    return policies


def evaluate_baselines(env: BatchedEnv, protocol: EvalProtocol) -> dict[str, EvalMetrics]:
    """The task's baselines (baseline_policies) on the protocol's env seed."""
    return {p.name: evaluate(env, p, protocol.steps, protocol.seed) for p in baseline_policies(env, protocol)}


def meets_bar(metrics: EvalMetrics, baselines: dict[str, EvalMetrics], supported: bool = False) -> bool:
    """The competence bar of the metrics' task against the baselines of the same evaluation: on point
    estimates (`navi bench learn`'s stop), or with `supported` an explore bar held across the 95% intervals,
    paired with the reactive baseline (competent_supported: the rule of the main job's verdict)."""
    if metrics.task == "pointgoal":
        return goal_competent(metrics, baselines["greedy"])
    reactive = baselines["reactive"]
    return competent_supported(metrics, reactive) if supported else competent(metrics, reactive)


def bar_status(metrics: EvalMetrics | None, baselines: dict[str, EvalMetrics]) -> str:
    """One line: the metrics (when given) beside the baseline the bar compares with."""
    if "greedy" in baselines:
        g = baselines["greedy"]
        if metrics is None:
            return f"unseen: greedy success {g.success_rate:.2f}, SPL {g.spl:.2f}, {g.collisions_per_episode:.2f} coll/ep"
        return (
            f"unseen: success {metrics.success_rate:.2f}, SPL {metrics.spl:.2f}, "
            f"{metrics.collisions_per_episode:.2f} coll/ep (greedy {g.success_rate:.2f}, {g.spl:.2f}, "
            f"{g.collisions_per_episode:.2f})"
        )
    r = baselines["reactive"]
    if metrics is None:
        return f"unseen: reactive {r.collisions_per_1k:.2f} coll/1k, {r.coverage_per_1k:.0f} cov/1k"
    return (
        f"unseen: {metrics.collisions_per_1k:.2f} coll/1k (reactive {r.collisions_per_1k:.2f}), "
        f"{metrics.coverage_per_1k:.0f} cov/1k (reactive {r.coverage_per_1k:.0f})"
    )


def curve_point(metrics: EvalMetrics, step: int, train_s: float, wall_s: float) -> dict[str, Any]:
    """One learning-curve point: env steps, training seconds, wall seconds, the metrics and intervals."""
    point: dict[str, Any] = {"step": step, "train_s": train_s, "wall_s": wall_s}
    for key in CURVE_KEYS:
        point[key] = getattr(metrics, key)
        point[f"{key}_ci"] = metrics.ci.get(key)
    return point


def eager_twin(policy: CognitiveMambaPolicy) -> CognitiveMambaPolicy:
    """A fresh policy of the same shape with `policy`'s weights and buffers, in eval mode, built as a
    loaded checkpoint is (CheckpointPolicy). Training compiles the live encoder in place on CUDA, whose
    fused kernels round otherwise than the eager encoder a checkpoint flies: near the bar the two flights
    could give opposite verdicts."""
    device = next(policy.parameters()).device
    twin = CognitiveMambaPolicy(policy.obs_shape, policy.cfg).to(device)
    twin.load_state_dict(policy.state_dict())
    return twin.eval()


@dataclass
class CompetenceMonitor:
    """A train() monitor: every `every_s` seconds of training it evaluates the live weights on `env`
    (the unseen scenes) with `protocol`, appends a curve point, and notes the first competent point.
    With `stop_at_competence` training ends there."""

    env: BatchedEnv
    protocol: EvalProtocol
    every_s: float
    stop_at_competence: bool = True
    say: Callable[[str], None] | None = None
    supported: bool = False
    """Competence as the main job's verdict judges it (meets_bar's `supported`): the explore bar held across
    the intervals, so that the job stops where its final verdict will say yes."""
    baselines: dict[str, EvalMetrics] = field(default_factory=dict)
    curve: list[dict[str, Any]] = field(default_factory=list)
    competence: dict[str, Any] | None = None
    latest: EvalMetrics | None = None
    status: str = ""

    def __post_init__(self) -> None:
        self.started = time.perf_counter()
        self.next_s = self.every_s
        if not self.baselines:
            self.baselines = evaluate_baselines(self.env, self.protocol)
        self.status = bar_status(None, self.baselines)

    def evaluate_policy(self, policy: CognitiveMambaPolicy, name: str = "trained") -> EvalMetrics:
        """Evaluation of `policy`'s weights on the unseen env, flown as its task is (ACTION_NOISE) by
        eager_twin(policy): the flight a checkpoint of these weights gets (CheckpointPolicy), so the
        evaluation that stops a run is the final verdict's."""
        flown = ModulePolicy(
            eager_twin(policy), name, action_noise(capabilities(self.env).task), self.protocol.seed
        )
        return evaluate(self.env, flown, self.protocol.steps, self.protocol.seed)

    def record(self, policy: CognitiveMambaPolicy, step: int, train_s: float) -> EvalMetrics:
        """Evaluate now and append the curve point; notes competence the first time it is reached."""
        m = self.evaluate_policy(policy)
        self.latest = m
        point = curve_point(m, step, train_s, time.perf_counter() - self.started)
        point["competent"] = meets_bar(m, self.baselines, self.supported)
        self.curve.append(point)
        if point["competent"] and self.competence is None:
            self.competence = {"step": step, "train_s": train_s, "wall_s": point["wall_s"]}
        self.status = bar_status(m, self.baselines) + (" COMPETENT" if point["competent"] else "")
        if self.say is not None:
            self.say(f"step {step:,} ({train_s:.0f} s) {self.status}")
        return m

    def __call__(self, policy: CognitiveMambaPolicy, step_id: int, train_s: float) -> bool:
        if train_s < self.next_s:
            return False
        self.next_s = train_s + self.every_s
        self.record(policy, step_id, train_s)
        return self.stop_at_competence and self.competence is not None

    def to_json(self) -> dict[str, Any]:
        """Protocol, baselines, curve and competence (NaN left as is; see evaluate.jsonable)."""
        return {
            "protocol": asdict(self.protocol),
            "baselines": {k: asdict(v) for k, v in self.baselines.items()},
            "curve": self.curve,
            "competence": self.competence,
        }


def plot_curves(
    runs: dict[str, list[dict[str, Any]]], baselines: dict[str, EvalMetrics], path: Path
) -> str | None:
    """Learning curves (collisions, coverage, return; against env steps and against training time),
    one line per run, the baselines as horizontal lines and the competence bars dotted. Returns None
    when the PNG was written, else why not."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed, so no plot was drawn (pip install matplotlib)"
    keys = (
        ("collisions_per_1k", "collisions / 1k steps"),
        ("coverage_per_1k", "coverage / 1k steps"),
        ("episode_return", "episode return"),
    )
    goal = "greedy" in baselines  # point-goal runs
    if goal:
        keys = (
            ("success_rate", "success rate"),
            ("spl", "SPL"),
            ("collisions_per_episode", "collisions / episode"),
        )
    bars = {"success_rate": 0.9, "spl": 0.75} if goal else {}
    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    reactive = baselines.get("reactive")
    for row, (xkey, xlabel) in enumerate((("step", "env steps"), ("train_s", "training seconds"))):
        for col, (key, label) in enumerate(keys):
            ax = axes[row][col]
            for name, points in runs.items():
                xs = [p[xkey] for p in points]
                ax.plot(xs, [p[key] for p in points], marker="o", markersize=3, label=name)
            for bname, style in (("random", ":"), ("reactive", "--"), ("greedy", "--"), ("oracle", "-.")):
                if bname in baselines:
                    ax.axhline(getattr(baselines[bname], key), linestyle=style, color="gray", label=bname)
            if key in bars:
                ax.axhline(bars[key], color="green", linewidth=0.8, label="competence")
            if reactive is not None and key == "collisions_per_1k" and not goal:
                ax.axhline(0.5 * reactive.collisions_per_1k, color="green", linewidth=0.8, label="competence")
            if reactive is not None and key == "coverage_per_1k":
                ax.axhline(1.5 * reactive.coverage_per_1k, color="green", linewidth=0.8, label="competence")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(label)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return None


def per_scene(
    corpus: Path,
    scenes: int,
    protocol: EvalProtocol,
    device: str,
    checkpoint: Path | None = None,
    reward: Mapping[str, float] | None = None,
) -> list[dict[str, EvalMetrics]]:
    """The reactive baseline (and the checkpoint, when given) on each of the corpus's `scenes` scenes alone,
    with `protocol` (its actors, steps, episode length and seed): one {policy name: metrics} per scene.
    `reward` replaces RewardConfig fields (make_env): the same flights scored by another reward, since
    neither policy reads the reward."""
    from navi_learner.envs.factory import make_env
    from navi_learner.evaluation.evaluate import CheckpointPolicy

    rows = []
    for s in range(scenes):
        env = make_env(corpus, protocol.actors, device, protocol.seed, episode_steps=protocol.episode_steps,
                       scene=s, reward=reward)  # fmt: skip
        policies: list[EvalPolicy] = [reactive_for_env(env)]
        if checkpoint is not None:
            policies.append(CheckpointPolicy(checkpoint, env.device, seed=protocol.seed))
        rows.append({p.name: evaluate(env, p, protocol.steps, protocol.seed) for p in policies})
    return rows
