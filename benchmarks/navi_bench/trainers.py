"""The trainers table: how soon does each trainer fly scenes it never saw better than the reactive avoider?

Protocol (docs/ENVIRONMENT.md, "Trainers compared"): one device, one corpus split (train, unseen), one
EnvConfig (the same traced view for every trainer). Each trainer trains from scratch on `actors` drones
of the train split for up to `budget_s` seconds of training time (its evaluations excluded):
- navi: Navi's own PPO (navi_learner.ppo.train with navi_learner.config.learning_recipe), its RayViT
  encoder over the full traced view and the chosen temporal core;
- rsl_rl, skrl, torchrl: PPO as the repository's examples configure it (examples/train_rsl_rl.py,
  train_skrl.py, train_torchrl.py), an MLP over the adapters' pooled 16 x 4 view.
Every `eval_every_s` seconds of training, and once at the end, the live policy's mean action flies the
unseen split (EvalProtocol: its actors, steps, episode length and seed) from the same spawns as the
reactive avoider and the random pilot. It beats the avoider at an evaluation where it has at most the
avoider's collisions per 1,000 steps (COLLISION_FLOOR_PER_1K where the avoider has none) and more
coverage per 1,000 steps; its run stops there. Reported per trainer: the training seconds and env steps
to the first such evaluation (None if none within the budget), the best evaluation reached (the first
that beat the avoider, else the one with the fewest collisions among those that out-cover it, else the
fewest collisions), the env-steps per second of training, the encoder, and every evaluation.

The examples are loaded from the repository's examples folder (EXAMPLES): the table measures the code a
user runs.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import make_batched_env
from navi_learner.config import TemporalCoreName, learning_recipe, learning_size
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.evaluation.baselines import EvalPolicy, RandomPolicy, reactive_for_env
from navi_learner.evaluation.competence import EvalProtocol, curve_point
from navi_learner.evaluation.evaluate import (
    EvalMetrics,
    ModulePolicy,
    collision_bar,
    competent,
    evaluate,
    jsonable,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
"""The repository's examples folder, where the stock trainers are configured."""
TRAINERS: tuple[str, ...] = ("navi", "rsl_rl", "skrl", "torchrl")
"""Every trainer of the table, in its order."""
EXAMPLE_OF = {"rsl_rl": "train_rsl_rl", "skrl": "train_skrl", "torchrl": "train_torchrl"}
"""The example module of each stock trainer."""
BAR = (
    "collisions/1k <= the reactive avoider's (0.5 where it has none) and coverage/1k > its, "
    "unseen split, same spawns"
)

Say = Callable[[str], None]


def say_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def beats_reactive(metrics: EvalMetrics, reactive: EvalMetrics) -> bool:
    """At most the avoider's collisions per 1,000 steps (COLLISION_FLOOR_PER_1K where it has none) and
    more coverage per 1,000 steps, on the same spawns."""
    return (
        metrics.collisions_per_1k <= collision_bar(reactive, 1.0)
        and metrics.coverage_per_1k > reactive.coverage_per_1k
    )


def best_point(curve: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The first point that beat the avoider; else the fewest collisions among the points that out-cover
    it; else the fewest collisions."""
    if not curve:
        return None
    beaten = [p for p in curve if p["beats_reactive"]]
    if beaten:
        return beaten[0]
    covering = [p for p in curve if p["covers_more"]] or curve
    return min(covering, key=lambda p: p["collisions_per_1k"])


class Curve:
    """The evaluations of one trainer's run on the unseen split, and when it first beat the avoider."""

    def __init__(self, env: Any, protocol: EvalProtocol, reactive: EvalMetrics, say: Say, name: str) -> None:
        self.env, self.protocol, self.reactive, self.say, self.name = env, protocol, reactive, say, name
        self.points: list[dict[str, Any]] = []
        self.beaten: dict[str, Any] | None = None
        self.started = time.perf_counter()

    def record(self, policy: EvalPolicy, env_steps: int, train_s: float) -> bool:
        """Evaluate `policy` now; True when it beats the avoider."""
        m = evaluate(self.env, policy, self.protocol.steps, self.protocol.seed)
        point = curve_point(m, env_steps, train_s, time.perf_counter() - self.started)
        point["beats_reactive"] = beats_reactive(m, self.reactive)
        point["covers_more"] = m.coverage_per_1k > self.reactive.coverage_per_1k
        point["competent"] = competent(m, self.reactive)
        self.points.append(point)
        if point["beats_reactive"] and self.beaten is None:
            self.beaten = {"train_s": train_s, "env_steps": env_steps, "wall_s": point["wall_s"]}
        r = self.reactive
        self.say(
            f"[bench trainers] {self.name}: {env_steps:,} steps ({train_s:.0f} s) "
            f"{m.collisions_per_1k:.2f} coll/1k (reactive {r.collisions_per_1k:.2f}), "
            f"{m.coverage_per_1k:.0f} cov/1k (reactive {r.coverage_per_1k:.0f})"
            + (" BEATS REACTIVE" if point["beats_reactive"] else "")
        )
        return bool(point["beats_reactive"])


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def load_example(trainer: str, examples: Path = EXAMPLES) -> ModuleType:
    """The example module of a stock trainer, imported from `examples`."""
    if not (examples / f"{EXAMPLE_OF[trainer]}.py").is_file():
        raise FileNotFoundError(
            f"{examples} holds no {EXAMPLE_OF[trainer]}.py: run from a checkout of the repository"
        )
    if str(examples) not in sys.path:
        sys.path.insert(0, str(examples))
    return importlib.import_module(EXAMPLE_OF[trainer])


def run_stock(
    trainer: str,
    train: Path,
    curve: Curve,
    config: EnvConfig,
    actors: int,
    device: str,
    seed: int,
    budget_s: float,
    eval_every_s: float,
) -> dict[str, Any]:
    """One stock trainer from its example: learn a rollout at a time until the budget or the avoider is
    beaten, evaluating every eval_every_s seconds of training and at the end."""
    learner = load_example(trainer).make(str(train), actors, config, device, seed)
    train_s, steps, next_eval = 0.0, 0, eval_every_s
    while True:
        t0 = time.perf_counter()
        learner.learn(learner.rollout)
        sync(device)
        train_s += time.perf_counter() - t0
        steps += learner.rollout * actors
        done = train_s >= budget_s
        if (train_s >= next_eval or done) and curve.record(learner.policy(), steps, train_s):
            break
        if done:
            break
        if train_s >= next_eval:
            next_eval = train_s + eval_every_s
    return {"encoder": learner.encoder, "train_s": train_s, "env_steps": steps}


class NaviMonitor:
    """navi_learner.ppo.train's monitor: evaluate the live policy every `every_s` seconds of training,
    stop once it beats the avoider."""

    def __init__(self, curve: Curve, every_s: float) -> None:
        self.curve, self.every_s, self.next_s = curve, every_s, every_s
        self.status = ""
        self.policy: CognitiveMambaPolicy | None = None
        self.step, self.train_s = 0, 0.0

    def record(self, policy: CognitiveMambaPolicy, step_id: int, train_s: float) -> bool:
        was_training = policy.training
        policy.eval()
        try:
            return self.curve.record(ModulePolicy(policy, "navi PPO"), step_id, train_s)
        finally:
            policy.train(was_training)

    def __call__(self, policy: CognitiveMambaPolicy, step_id: int, train_s: float) -> bool:
        self.policy, self.step, self.train_s = policy, step_id, train_s
        if train_s < self.next_s:
            return False
        self.next_s = train_s + self.every_s
        return self.record(policy, step_id, train_s)


def run_navi(
    train: Path,
    curve: Curve,
    config: EnvConfig,
    actors: int,
    device: str,
    seed: int,
    budget_s: float,
    eval_every_s: float,
    core: TemporalCoreName,
    work_dir: Path,
) -> dict[str, Any]:
    """Navi's own PPO with the learning recipe, `actors` drones, `core`, the time budget."""
    from navi_learner.ppo.train import train as train_navi

    recipe = learning_size(learning_recipe(), torch.device(device))
    tcfg = replace(
        recipe,
        n_actors=actors,
        time_limit_s=budget_s,
        checkpoint_every=10**12,
        seed=seed,
        device=device,
        engine=replace(recipe.engine, temporal_core=core),
    )
    env = make_batched_env(train, actors, device, config, seed=seed)
    monitor = NaviMonitor(curve, eval_every_s)
    result = train_navi(env, tcfg, run_dir=work_dir / "navi", progress=False, monitor=monitor)
    train_s = float(result.last_metrics.get("train_s", monitor.train_s))
    last = curve.points[-1]["step"] if curve.points else None
    if monitor.policy is not None and curve.beaten is None and last != result.step_id:
        monitor.record(monitor.policy, result.step_id, train_s)  # the budget ended between evaluations
    engine = tcfg.engine
    az, el = env.obs_shape[1], env.obs_shape[2]
    encoder = f"RayViT ({engine.encoder_layers} layers, D {engine.embed_dim}) + {core} over the full {az} x {el} view"
    return {"encoder": encoder, "train_s": train_s, "env_steps": result.step_id}


def bench_trainers(
    train: Path,
    unseen: Path,
    work_dir: Path,
    device: str = "cuda",
    config: EnvConfig | None = None,
    actors: int = 2048,
    budget_s: float = 600.0,
    eval_every_s: float = 30.0,
    trainers: Sequence[str] = TRAINERS,
    seed: int = 0,
    protocol: EvalProtocol | None = None,
    navi_core: TemporalCoreName = "mamba2",
    say: Say = say_stderr,
) -> dict[str, Any]:
    """Train each of `trainers` (TRAINERS: navi, rsl_rl, skrl, torchrl) on `actors` drones of the `train`
    corpus folder for up to `budget_s` training seconds on `device`, evaluating it on the `unseen` corpus
    folder every `eval_every_s` training seconds against the reactive avoider (see the module docstring);
    `config` is every env's EnvConfig (default EnvConfig(): 256 x 48 rays), `protocol` the evaluation
    (default EvalProtocol.for_device), `navi_core` the temporal core of Navi's own PPO, `work_dir` where
    its run folder goes. Returns a JSON-able dict: device, date, settings, baselines (random, reactive),
    and per trainer encoder, train_s, env_steps, env_steps_per_s, beat_reactive (train_s, env_steps,
    wall_s of the first evaluation that beat the avoider, or None), best (an evaluation point) and curve
    (every evaluation point: env steps, train_s, wall_s, the metrics with their 95% intervals)."""
    unknown = [t for t in trainers if t not in TRAINERS]
    if unknown:
        raise ValueError(f"unknown trainers {unknown}; choose from {', '.join(TRAINERS)}")
    if budget_s <= 0 or eval_every_s <= 0:
        raise ValueError("budget_s and eval_every_s must be positive")
    cfg = config or EnvConfig()
    p = protocol or EvalProtocol.for_device(torch.device(device))
    eval_config = replace(cfg, max_steps_per_episode=p.episode_steps)
    unseen_env = make_batched_env(unseen, p.actors, device, eval_config, seed=p.seed)
    random_m = evaluate(unseen_env, RandomPolicy(p.seed), p.steps, p.seed)
    reactive = evaluate(unseen_env, reactive_for_env(unseen_env), p.steps, p.seed)
    say(
        f"[bench trainers] unseen: reactive {reactive.collisions_per_1k:.2f} coll/1k, "
        f"{reactive.coverage_per_1k:.0f} cov/1k; random {random_m.collisions_per_1k:.2f}, {random_m.coverage_per_1k:.0f}"
    )
    results: dict[str, Any] = {}
    for trainer in trainers:
        curve = Curve(unseen_env, p, reactive, say, trainer)
        started = time.perf_counter()
        # what a library prints while it trains (rsl_rl's runner prints its models and every iteration)
        # goes to stderr: stdout stays the benchmark's own, one JSON object under --json
        with contextlib.redirect_stdout(sys.stderr):
            if trainer == "navi":
                run = run_navi(
                    train, curve, cfg, actors, device, seed, budget_s, eval_every_s, navi_core, work_dir
                )
            else:
                run = run_stock(trainer, train, curve, cfg, actors, device, seed, budget_s, eval_every_s)
        results[trainer] = run | {
            "env_steps_per_s": run["env_steps"] / run["train_s"] if run["train_s"] > 0 else math.nan,
            "beat_reactive": curve.beaten,
            "best": best_point(curve.points),
            "curve": curve.points,
            "wall_s": time.perf_counter() - started,
        }
        gc.collect()  # the trainer's env, networks and rollouts go before the next one starts
        if device.startswith("cuda"):
            torch.cuda.empty_cache()
    out = {
        "device": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "train": str(train),
        "unseen": str(unseen),
        "settings": {
            "actors": actors,
            "budget_s": budget_s,
            "eval_every_s": eval_every_s,
            "seed": seed,
            "view": [cfg.azimuth_bins, cfg.elevation_bins],
            "navi_core": navi_core,
            "protocol": asdict(p),
        },
        "bar": BAR,
        "baselines": {"random": asdict(random_m), "reactive": asdict(reactive)},
        "trainers": results,
    }
    result = jsonable(out)
    assert isinstance(result, dict)
    return result
