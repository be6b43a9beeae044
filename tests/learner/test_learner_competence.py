"""Evaluation statistics, the competence monitor and `navi bench learn` end to end on a CPU.

- evaluate() against a slow per-actor twin written out step by step: finished-episode returns only
  (NaN when no episode finished), per-actor sums, coverage as distinct cells per actor-episode, and
  bootstrap intervals that contain the estimate and repeat exactly.
- The monitor evaluates at its cadence, marks exactly the points that pass the bar, and stops training
  at the first one when asked.
- bench learn writes the split, the baselines, one curve per run, the summary and the plot.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from navi_bench.learn import (
    LearnConfig,
    arm_reward,
    bench_learn,
    censored_median,
    gpu_lanes,
    late_means,
    parse_arm,
    report_markdown,
    run_devices,
    run_order,
    train_config,
)
from navi_bench.learn import summarise as summarise_arms
from navi_env.corpus.folder import build_default_corpus
from navi_env.corpus.openarena import split_openarena
from navi_learner.config import TASK_LR, TASK_RATE, EngineConfig, PPOConfig, TrainConfig, learning_recipe
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.envs.factory import make_env, parse_reward_overrides, reward_config
from navi_learner.envs.protocol import StepLike, capabilities
from navi_learner.envs.toy import ToyEnv
from navi_learner.evaluation.baselines import RandomPolicy
from navi_learner.evaluation.competence import CompetenceMonitor, EvalProtocol, meets_bar
from navi_learner.evaluation.evaluate import (
    COLLISION_FLOOR_PER_1K,
    ActorSums,
    EvalMetrics,
    ModulePolicy,
    action_noise,
    beats_supported,
    competent,
    competent_supported,
    contact_line,
    contact_spread,
    evaluate,
    goal_competent,
    mean_outside_line,
    paired_intervals,
    summarise,
)
from navi_learner.ppo.train import train

ENGINE = EngineConfig.tiny()

pytestmark = pytest.mark.usefixtures("single_thread")


def evaluate_ref(env: ToyEnv, policy: RandomPolicy, steps: int, seed: int) -> dict[str, float]:
    """Slow twin of evaluate(): Python bookkeeping per actor and step."""
    n = env.n_actors
    policy.reset(n, torch.device("cpu"))
    obs, resets = env.reset(seed=seed), torch.ones(n, dtype=torch.bool)
    running, finished, episodes, reward = [0.0] * n, [], 0, 0.0
    cells: list[set[tuple[int, int, int, int]]] = [set() for _ in range(n)]
    episode = [0] * n
    for _ in range(steps):
        out = env.step(policy.act(obs, resets))
        for i in range(n):
            r = float(out.reward[i])
            running[i] += r
            reward += r
            x, y, z = (math.floor(float(v)) for v in out.info["position"][i])
            cells[i].add((episode[i], x, y, z))
            if bool(out.truncated[i] | out.done[i]):
                finished.append(running[i])
                running[i], episodes, episode[i] = 0.0, episodes + 1, episode[i] + 1
        obs, resets = out.obs, out.done | out.truncated
    return {
        "episodes": episodes,
        "episode_return": sum(finished) / episodes if episodes else math.nan,
        "reward_per_step": reward / (n * steps),
        "coverage_per_1k": 1000.0 * sum(len(c) for c in cells) / (n * steps),
    }


@pytest.mark.parametrize("max_steps", [16, 10**6])
def test_evaluate_matches_its_slow_twin(max_steps: int) -> None:
    fast = evaluate(ToyEnv(6, seed=4, max_steps=max_steps), RandomPolicy(9), 40, seed=4)
    slow = evaluate_ref(ToyEnv(6, seed=4, max_steps=max_steps), RandomPolicy(9), 40, seed=4)
    assert fast.episodes == slow["episodes"]
    if max_steps > 40:  # counters start in [0, 1e6): no episode can finish, so there is no return
        assert slow["episodes"] == 0 and math.isnan(fast.episode_return)
    else:
        assert fast.episode_return == pytest.approx(slow["episode_return"], rel=1e-9, abs=1e-9)
    assert fast.reward_per_step == pytest.approx(slow["reward_per_step"], rel=1e-6, abs=1e-9)
    assert fast.coverage_per_1k == pytest.approx(slow["coverage_per_1k"])


def test_bootstrap_intervals_contain_the_estimate_and_repeat() -> None:
    a = evaluate(ToyEnv(32, seed=1, max_steps=16), RandomPolicy(2), 48, seed=1)
    b = evaluate(ToyEnv(32, seed=1, max_steps=16), RandomPolicy(2), 48, seed=1)
    assert a.ci == b.ci
    for key in ("reward_per_step", "coverage_per_1k", "distance_per_1k", "episode_return"):
        lo, hi = a.ci[key]
        assert lo <= getattr(a, key) <= hi and lo < hi, key
    lo, hi = a.ci["coverage_per_1k"]  # across 32 actors the spread is real, not a point
    assert np.isfinite([lo, hi]).all()


def metrics(collisions: float, coverage: float) -> EvalMetrics:
    return EvalMetrics("x", 1, 1, 0, math.nan, 0.0, collisions, 1.0, coverage, 0.0, 0.0, 1.0)


def test_competence_bar() -> None:
    reactive = metrics(2.0, 100.0)
    assert competent(metrics(1.0, 150.0), reactive)
    assert not competent(metrics(1.01, 150.0), reactive)
    assert not competent(metrics(0.0, 149.9), reactive)
    assert competent(metrics(0.0, 150.0), metrics(0.0, 100.0))  # 0 against 0 meets "half as many"
    # Where the reactive baseline has none, the bar is the floor of 0.5 collisions per 1k.
    assert competent(metrics(COLLISION_FLOOR_PER_1K, 150.0), metrics(0.0, 100.0))
    assert not competent(metrics(0.51, 500.0), metrics(0.0, 100.0))


def flown(name: str, cells: np.ndarray, collision: np.ndarray, steps: int = 500) -> EvalMetrics:
    """EvalMetrics of actors that covered `cells` and collided `collision` times in `steps` steps each."""
    n = cells.shape[0]
    zeros = np.zeros(n)
    sums = ActorSums(
        steps=np.full(n, float(steps)), reward=zeros, finished_return=zeros, episodes=np.full(n, 2.0),
        collision=collision.astype(float), obstacle_collision=zeros, clearance=zeros, starved=zeros,
        distance=zeros, cells=cells.astype(float), success=zeros, spl=zeros, soft_spl=zeros, goal_seconds=zeros,
    )  # fmt: skip
    return summarise(name, sums, steps, {"collision": True, "position": True}, 1.0)


def paired_ref(a: EvalMetrics, b: EvalMetrics, samples: int, seed: int) -> dict[str, list[float]]:
    """Slow twin of paired_intervals: one resample at a time, sums in Python."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, a.actors, size=(samples, a.actors))
    ratios, diffs = [], []
    for row in idx:
        cover_a = sum(a.per_actor["cells"][i] for i in row) / sum(a.per_actor["steps"][i] for i in row)
        cover_b = sum(b.per_actor["cells"][i] for i in row) / sum(b.per_actor["steps"][i] for i in row)
        coll_a = sum(a.per_actor["collision"][i] for i in row) / sum(a.per_actor["steps"][i] for i in row)
        coll_b = sum(b.per_actor["collision"][i] for i in row) / sum(b.per_actor["steps"][i] for i in row)
        ratios.append(cover_a / cover_b)
        diffs.append(1000.0 * (coll_a - coll_b))
    return {
        "coverage_ratio": [float(np.percentile(ratios, 2.5)), float(np.percentile(ratios, 97.5))],
        "collision_difference": [float(np.percentile(diffs, 2.5)), float(np.percentile(diffs, 97.5))],
    }


def test_paired_intervals_match_their_slow_twin() -> None:
    rng = np.random.default_rng(4)
    a = flown("a", rng.integers(20, 200, 12), rng.integers(0, 3, 12))
    b = flown("b", rng.integers(20, 200, 12), rng.integers(0, 3, 12))
    fast, slow = paired_intervals(a, b, samples=300, seed=7), paired_ref(a, b, samples=300, seed=7)
    for key in ("coverage_ratio", "collision_difference"):
        assert fast[key] == pytest.approx(slow[key], rel=1e-12, abs=1e-12), key


def test_pairing_sees_a_win_that_the_spread_between_scenes_hides() -> None:
    """Scenes differ far more than the two pilots do: each one's own coverage interval overlaps the other's
    1.5x, but flown from the same spawns the ratio is tight, so the verdict holds (and fails at 1.4x)."""
    rng = np.random.default_rng(0)
    base = rng.uniform(30.0, 150.0, 48)  # (N,) how much room each actor's scene gives
    reactive = flown("reactive", np.round(base), np.zeros(48))
    good = flown("good", np.round(1.65 * base * rng.uniform(0.97, 1.03, 48)), np.zeros(48))
    short = flown("short", np.round(1.4 * base * rng.uniform(0.97, 1.03, 48)), np.zeros(48))
    assert good.ci["coverage_per_1k"][0] < 1.5 * reactive.ci["coverage_per_1k"][1]  # marginals overlap
    assert paired_intervals(good, reactive)["coverage_ratio"][0] >= 1.5
    assert competent_supported(good, reactive) and beats_supported(good, reactive)
    assert not competent_supported(short, reactive) and beats_supported(short, reactive)
    crashes = np.zeros(48)
    crashes[:12] = 3  # 36 contacts in 24,000 steps: 1.5 per 1k, above the 0.5 floor across the interval
    crashing = flown("crashing", np.round(1.65 * base), crashes)
    assert competent(crashing, reactive) is False and not competent_supported(crashing, reactive)
    assert not beats_supported(crashing, reactive)
    one = np.zeros(48)
    one[0] = 1  # a single contact: 0.04 per 1k, its interval within the floor
    assert competent_supported(
        flown("once", np.round(1.65 * base * rng.uniform(0.97, 1.03, 48)), one), reactive
    )


def test_the_main_jobs_stop_rule_is_the_rule_of_its_verdict() -> None:
    """A drone that covers 1.55x reactive on average, but 1.1x to 2.0x actor by actor, passes the bar on
    point estimates (`navi bench learn` stops there) and not across the paired interval, the rule of the
    main job's final verdict, which its monitor stops on (supported); a tight 1.65x passes both. Point-goal
    bars are point estimates either way."""
    rng = np.random.default_rng(1)
    base = rng.uniform(30.0, 150.0, 48)  # (N,)
    reactive = flown("reactive", np.round(base), np.zeros(48))
    spread = flown("spread", np.round(base * np.linspace(1.1, 2.0, 48)), np.zeros(48))
    tight = flown("tight", np.round(1.65 * base * rng.uniform(0.98, 1.02, 48)), np.zeros(48))
    baselines = {"reactive": reactive}
    ratio = spread.coverage_per_1k / reactive.coverage_per_1k
    assert ratio >= 1.5 and meets_bar(spread, baselines) and not meets_bar(spread, baselines, supported=True)
    assert meets_bar(tight, baselines) and meets_bar(tight, baselines, supported=True)
    greedy = goal_metrics(0.7, 0.7, 2.0)
    for supported in (False, True):
        assert meets_bar(goal_metrics(0.9, 0.75, 1.9), {"greedy": greedy}, supported)


def test_paired_intervals_need_the_same_flight() -> None:
    a = flown("a", np.full(8, 50), np.zeros(8))
    with pytest.raises(ValueError, match="same actors"):
        paired_intervals(a, flown("b", np.full(9, 50), np.zeros(9)))
    with pytest.raises(ValueError, match="per-actor sums"):
        paired_intervals(a, metrics(0.0, 50.0))


def goal_metrics(success: float, spl: float, collisions: float) -> EvalMetrics:
    base = metrics(0.0, 0.0)
    return replace(base, success_rate=success, spl=spl, collisions_per_episode=collisions, task="pointgoal")


def test_point_goal_bar() -> None:
    greedy = goal_metrics(0.7, 0.7, 2.0)
    assert goal_competent(goal_metrics(0.9, 0.75, 1.9), greedy)
    assert not goal_competent(goal_metrics(0.89, 0.9, 0.0), greedy)
    assert not goal_competent(goal_metrics(0.95, 0.74, 0.0), greedy)
    assert not goal_competent(goal_metrics(0.95, 0.9, 2.0), greedy)  # fewer collisions than greedy
    assert goal_competent(goal_metrics(0.95, 0.9, 0.0), goal_metrics(0.5, 0.5, 0.0))  # none against none


def toy_config(total: int) -> TrainConfig:
    ppo = PPOConfig(lr=2e-3, num_minibatches=2, bptt_chunk=16, ppo_epochs=1)
    return TrainConfig(
        n_actors=8, rollout_length=16, total_steps=total, engine=ENGINE, ppo=ppo, checkpoint_every=10**9
    )


def test_monitor_marks_competent_points_and_keeps_going_when_told(tmp_path: Path) -> None:
    protocol = EvalProtocol(actors=8, steps=32, episode_steps=16, seed=3)
    monitor = CompetenceMonitor(
        ToyEnv(8, seed=3, max_steps=16), protocol, every_s=1e-6, stop_at_competence=False
    )
    result = train(
        ToyEnv(8, seed=0), toy_config(8 * 16 * 4), run_dir=tmp_path / "run", progress=False, monitor=monitor
    )
    assert result.step_id == 8 * 16 * 4  # not stopped
    assert [p["step"] for p in monitor.curve] == [128, 256, 384, 512]
    assert all(a["train_s"] < b["train_s"] for a, b in zip(monitor.curve, monitor.curve[1:], strict=False))
    reactive = monitor.baselines["reactive"]
    for p in monitor.curve:
        assert p["competent"] == competent(metrics(p["collisions_per_1k"], p["coverage_per_1k"]), reactive)
    first = next((p for p in monitor.curve if p["competent"]), None)
    assert monitor.competence == (
        None if first is None else {k: first[k] for k in ("step", "train_s", "wall_s")}
    )


def test_monitor_stops_training_at_the_first_competent_point(tmp_path: Path) -> None:
    protocol = EvalProtocol(actors=8, steps=32, episode_steps=16, seed=3)
    beaten = {"random": metrics(math.inf, 0.0), "reactive": metrics(math.inf, 0.0)}  # every policy passes
    monitor = CompetenceMonitor(ToyEnv(8, seed=3, max_steps=16), protocol, every_s=1e-6, baselines=beaten)
    result = train(
        ToyEnv(8, seed=0), toy_config(10**6), run_dir=tmp_path / "run", progress=False, monitor=monitor
    )
    assert result.step_id == 128 and len(monitor.curve) == 1
    assert monitor.competence is not None and monitor.competence["step"] == 128


def test_monitor_flies_the_weights_as_their_checkpoint_does() -> None:
    """Training compiles the live encoder in place on CUDA, and its fused kernels fly other numbers than
    the eager encoder of a loaded checkpoint. The monitor flies an eager twin with the live weights: a
    live module that computes otherwise leaves its evaluation as it is, and that evaluation is a loaded
    copy's flight."""
    env = ToyEnv(8, seed=3, max_steps=16)
    protocol = EvalProtocol(actors=8, steps=32, episode_steps=16, seed=3)
    beaten = {"random": metrics(math.inf, 0.0), "reactive": metrics(math.inf, 0.0)}
    monitor = CompetenceMonitor(env, protocol, every_s=1.0, baselines=beaten)
    torch.manual_seed(0)
    policy = CognitiveMambaPolicy(env.obs_shape, ENGINE)

    def flight(m: EvalMetrics) -> dict[str, object]:
        return {k: v for k, v in asdict(m).items() if k not in ("sps", "policy")}

    plain = monitor.evaluate_policy(policy)
    loaded = CognitiveMambaPolicy(env.obs_shape, ENGINE)
    loaded.load_state_dict(policy.state_dict())
    noise = action_noise(capabilities(env).task)
    copy = evaluate(
        env, ModulePolicy(loaded.eval(), "copy", noise, protocol.seed), protocol.steps, protocol.seed
    )
    assert flight(copy) == flight(plain)
    forward = policy.encoder.forward
    policy.encoder.forward = lambda obs, dtype=None: forward(obs, dtype) + 1.0  # type: ignore[method-assign]
    live = evaluate(
        env, ModulePolicy(policy.eval(), "live", noise, protocol.seed), protocol.steps, protocol.seed
    )
    assert live.episode_return != plain.episode_return  # the live module flies otherwise
    assert flight(monitor.evaluate_policy(policy)) == flight(plain)


def test_an_evaluation_reports_how_often_the_action_means_lie_outside_the_clip_box() -> None:
    """A trained policy's evaluation counts, per action axis, the actor-steps whose mean lay outside
    [-1, 1]: all of them on the axis whose mean is pushed to 1.5, none on an axis held at 0, the same
    whether the flight samples or takes the mean; a baseline has no mean and reports nothing."""
    env = ToyEnv(8, seed=3, max_steps=16)
    torch.manual_seed(0)
    policy = CognitiveMambaPolicy(env.obs_shape, ENGINE).eval()
    mean_out = policy.heads.actor[-1]
    assert isinstance(mean_out, torch.nn.Linear)
    with torch.no_grad():
        mean_out.weight.zero_()
        mean_out.bias.copy_(torch.tensor([1.5, 0.0, -0.5, -2.0]))  # (4,) every step's mean
    for noise in (0.0, 1.0):
        m = evaluate(env, ModulePolicy(policy, "pushed", noise, seed=3), 32, seed=3)
        assert m.mean_outside == [1.0, 0.0, 0.0, 1.0]
        assert mean_outside_line(m).endswith("(pushed): 100.0% / 0.0% / 0.0% / 100.0%")
    baseline = evaluate(env, RandomPolicy(seed=0), 32, seed=3)
    assert baseline.mean_outside == [] and mean_outside_line(baseline) == ""


def test_split_openarena_holds_out_every_fifth_map() -> None:
    maps = [f"m{i:02d}" for i in range(12)]
    train_maps, held = split_openarena(maps)
    assert held == ["m00", "m05", "m10"] and set(train_maps) | set(held) == set(maps)
    assert not set(train_maps) & set(held)


def small_learn_config(task: str = "explore", **overrides: object) -> LearnConfig:
    """A bench learn job of seconds on a CPU: the gru core, 4 actors, a one-second budget, a tiny protocol."""
    train = replace(learning_recipe(), n_actors=4, rollout_length=16, compile=False, task=task)
    small: dict[str, object] = dict(
        temporal_cores=("gru",),
        time_budget_s=1.0,
        eval_every_s=0.5,
        train=train,
        protocol=EvalProtocol(actors=4, steps=24, episode_steps=12, seed=5),
        warmup_updates=0,
    )
    return LearnConfig(**(small | overrides))  # type: ignore[arg-type]


def test_median_to_competence_counts_the_seeds_that_never_got_there() -> None:
    # One seed of three competent: the median seed never got there, so there is no median time.
    assert censored_median([62.0, None, None]) is None
    assert censored_median([62.0, 162.0, None]) == 162.0
    assert censored_median([41.0, 82.0, 164.0]) == 82.0
    assert censored_median([30.0, None]) is None and censored_median([30.0, 50.0]) == 40.0
    assert censored_median([]) is None

    def run(arm: str, seed: int, hit: float | None) -> dict[str, object]:
        point = {
            "step": 100 * seed,
            "train_s": 120.0,
            "collisions_per_1k": 0.1 * seed,
            "coverage_per_1k": 200.0 + seed,
        }
        competence = None if hit is None else {"train_s": hit, "step": int(hit) * 1000}
        return {"arm": arm, "seed": seed, "competence": competence, "curve": [point], "sps": 1e5 + seed}

    runs = [run("a", 0, 121.0), run("b", 0, None), run("a", 1, None), run("b", 1, 40.0)]
    runs += [run("a", 2, None), run("b", 2, 90.0)]
    summary = summarise_arms(runs, budget_s=120.0)
    assert list(summary) == ["a", "b"]
    a, b = summary["a"], summary["b"]
    assert a["competent_seeds"] == 1 and a["median_train_s_to_competence"] is None
    assert a["median_steps_to_competence"] is None and not a["competent_within_budget"]
    assert b["competent_seeds"] == 2 and b["median_train_s_to_competence"] == 90.0
    assert b["median_steps_to_competence"] == 90_000
    assert b["median_final_collisions_per_1k"] == pytest.approx(0.1)


def test_late_means_average_the_second_half_of_the_budget_only() -> None:
    def point(train_s: float, coll: float, cov: float) -> dict[str, object]:
        return {
            "train_s": train_s,
            "step": int(train_s) * 1000,
            "collisions_per_1k": coll,
            "coverage_per_1k": cov,
        }

    # Evaluations every 20 s of a 120 s budget: those from 60 s on are the late ones.
    curve = [point(20, 0.9, 100.0), point(40, 0.5, 200.0), point(61, 0.2, 280.0), point(81, 0.05, 300.0)]
    curve += [point(101, 0.35, 320.0), point(120, 0.02, 310.0)]
    late = late_means(curve, budget_s=120.0)
    assert late["evaluations"] == 4
    assert late["collisions_per_1k"] == pytest.approx((0.2 + 0.05 + 0.35 + 0.02) / 4)
    assert late["coverage_per_1k"] == pytest.approx((280 + 300 + 320 + 310) / 4)
    assert late["success_rate"] is None and late["spl"] is None  # explore curves carry neither
    # A run stopped at competence before half its budget has no late evaluations.
    early = late_means(curve[:2], budget_s=120.0)
    assert early["evaluations"] == 0 and early["collisions_per_1k"] is None

    # The summary's late figure is the median over seeds of each seed's late mean: a seed whose last
    # evaluation drew 0.02 after a late mean of 0.155 moves its final figure, not its late one.
    def run(seed: int, points: list[dict[str, object]]) -> dict[str, object]:
        return {
            "arm": "a",
            "seed": seed,
            "competence": None,
            "curve": points,
            "sps": 2e5,
            "steps": 1,
            "train_s": 120.0,
        }

    runs = [run(0, curve), run(1, [point(70, 0.4, 250.0), point(120, 0.1, 260.0)]), run(2, curve[:2])]
    summary = summarise_arms(runs, budget_s=120.0)["a"]
    assert summary["median_late_collisions_per_1k"] == pytest.approx((0.155 + 0.25) / 2)  # seed 2 has none
    assert summary["median_final_collisions_per_1k"] == pytest.approx(0.1)
    result = {"device": "cpu", "date": "now", "config": {"train": {}}, "summary": {"a": summary}, "runs": []}
    text = report_markdown(result, {})
    assert "| late coll/1k | late cov/1k |" in text and "from 60 s of training" in text
    assert f"| {summary['median_late_collisions_per_1k']:.4g} |" in text


def test_the_report_shows_how_few_drones_make_the_contacts() -> None:
    """contact_spread on hand-made counts, then the stored collision A/B's report: its default seed 2 on
    the held-out maps had 9 of 256 actors touch anything and one of them make 479 of the 507 steps."""
    assert contact_spread({"collision": [0.0, 4.0, 0.0, 1.0, 7.0, 2.0]}) == {
        "actors": 6,
        "actors_in_contact": 4,
        "contact_steps": 14,
        "busiest_steps": 13,
        "most": 7,
    }
    assert contact_spread({}) is None
    stored = Path(__file__).resolve().parents[2] / "benchmarks/results/learn-collision-2026-12-01-H200"
    result = json.loads((stored / "result.json").read_text())
    baselines = {
        part: {name: EvalMetrics(**m) for name, m in b.items()} for part, b in result["baselines"].items()
    }
    text = report_markdown(result, baselines)
    section = text.split("## mamba2 seed 2, unseen openarena", 1)[1].split("\n## ", 1)[0]
    assert (
        "Contacts (trained): 9 of 256 actors touched a surface; the 3 busiest made 491 of the 507" in section
    )
    assert "(one actor 479)" in section
    # The same sentence under `navi run`'s and `navi evaluate`'s tables (contact_line), for any policy name.
    drone = EvalMetrics(**next(r for r in result["runs"] if r["seed"] == 2)["final_by_split"]["openarena"])
    assert contact_line(drone) in section
    assert contact_line(drone, "v001").startswith("Contacts (v001): 9 of 256 actors touched a surface")
    assert contact_line(replace(drone, per_actor={})) == ""  # no per-actor counts kept
    untouched = replace(drone, per_actor={"collision": [0.0] * 256})
    assert contact_line(untouched) == ""


def test_bench_learn_end_to_end_on_a_cpu(tmp_path: Path) -> None:
    root = tmp_path / "corpora"
    build_default_corpus(root / "procedural-train-64", resolution=64, count=2, seed=0)
    build_default_corpus(root / "procedural-unseen-64", resolution=64, count=1, seed=1000)
    # Two arms of one seed: the recipe's 4 actors, and an arm that trains 2 in their place.
    cfg = small_learn_config(
        seeds=(0,), temporal_cores=("gru", "gru/actors=2"), reward=(("exploration_weight", 0.25),)
    )
    out = tmp_path / "out"
    result = bench_learn(cfg, out, "cpu", 64, root, None, say=lambda _: None)
    saved = json.loads((out / "result.json").read_text())
    assert saved["reward"]["exploration_weight"] == 0.25 and saved["reward"]["proximity_weight"] == 0.2
    assert saved["splits"]["scenes"] == {
        "train/procedural": ["rooms_0000", "corridors_0001"],
        "unseen/procedural": ["rooms_0000"],
    }
    assert any("OpenArena" in note for note in saved["splits"]["notes"])
    assert set(saved["baselines"]) == {"all", "procedural"}
    runs = saved["runs"]
    assert [(r["arm"], r["temporal_core"], r["seed"]) for r in runs] == [
        ("gru", "gru", 0),
        ("gru/actors=2", "gru", 0),
    ]
    assert [r["train_config"]["n_actors"] for r in runs] == [4, 2]
    assert all(r["train_config"]["ppo"]["lr"] == 6e-4 for r in runs)  # the explore rate it trained at
    curves = json.loads((out / "curves.json").read_text())
    for run in runs:
        assert run["curve"] and run["curve"][-1]["step"] == run["steps"] and run["train_s"] >= 1.0
        assert run["steps"] % (run["train_config"]["n_actors"] * 16) == 0  # whole rollouts of its actors
        assert curves[f"{run['arm']} seed 0"] == run["curve"]
        assert set(run["final_by_split"]) == {"procedural"}
    for arm in ("gru", "gru/actors=2"):
        summary = result["summary"][arm]
        assert summary["seeds"] == 1
        assert summary["competent_seeds"] == sum(r["competence"] is not None for r in runs if r["arm"] == arm)
        assert f"| {arm} | 1 |" in (out / "report.md").read_text()
    assert (out / "learning_curves.png").stat().st_size > 10_000
    assert saved["warmups"] == []  # small_learn_config turns it off


def test_bench_learn_point_goal_end_to_end_on_a_cpu(tmp_path: Path) -> None:
    root = tmp_path / "corpora"
    build_default_corpus(root / "procedural-train-64", resolution=64, count=1, seed=0)
    build_default_corpus(root / "procedural-unseen-64", resolution=64, count=1, seed=1000)
    cfg = small_learn_config(seeds=(0,), task="pointgoal")
    out = tmp_path / "out"
    result = bench_learn(cfg, out, "cpu", 64, root, None, say=lambda _: None)
    saved = json.loads((out / "result.json").read_text())
    assert saved["config"]["train"]["task"] == "pointgoal" and "SPL" in saved["competence_bar"]
    assert set(saved["baselines"]["all"]) == {"random", "greedy", "oracle"}
    assert all(b["task"] == "pointgoal" for b in saved["baselines"]["all"].values())
    (run,) = saved["runs"]
    assert (
        run["train_config"]["task"] == "pointgoal"
        and run["train_config"]["ppo"]["lr"] == TASK_LR["pointgoal"]
    )
    assert all(p["competent"] is not None and "success_rate" in p for p in run["curve"])
    assert run["final_by_split"]["procedural"]["task"] == "pointgoal"
    assert "median_final_spl" in result["summary"]["gru"]
    assert "| success_rate |" in (out / "report.md").read_text()
    assert (out / "learning_curves.png").stat().st_size > 10_000


def test_reward_overrides_change_exactly_the_named_term(tmp_path: Path) -> None:
    corpus = tmp_path / "c"
    build_default_corpus(corpus, resolution=64, count=1, seed=0)
    plain = make_env(corpus, 4, "cpu", 3)
    taxed = make_env(corpus, 4, "cpu", 3, reward=parse_reward_overrides(["existential_tax=-0.5"]))
    assert taxed.config.reward.existential_tax == -0.5  # type: ignore[attr-defined]
    plain.reset(seed=3)
    taxed.reset(seed=3)
    action = torch.tensor([[0.5, 0.0, 0.1, 0.2]]).repeat(4, 1)  # (N, 4)
    for _ in range(5):  # same seed, same actions: only the constant term differs
        a, b = plain.step(action), taxed.step(action)
        torch.testing.assert_close(b.reward - a.reward, torch.full((4,), -0.48), rtol=0, atol=1e-5)
    for bad in (["existential_tax"], ["no_such_weight=1"], ["exploration_table_bits=3"]):
        with pytest.raises(ValueError):
            parse_reward_overrides(bad)
    with pytest.raises(ValueError, match="explore episodes do not read pointgoal_collision_weight"):
        make_env(corpus, 4, "cpu", 3, reward={"pointgoal_collision_weight": 9.0})


def test_a_collision_weight_the_task_does_not_read_is_refused(tmp_path: Path) -> None:
    """Each task prices contacts with its own weight, so overriding the other task's fails with the name
    of the right one, in make_env and before a bench learn job builds anything."""
    assert reward_config({"pointgoal_collision_weight": 5.0}, "pointgoal").pointgoal_collision_weight == 5.0
    assert reward_config({"collision_weight": 9.0}, "explore").collision_weight == 9.0
    with pytest.raises(ValueError, match="their collision weight is pointgoal_collision_weight"):
        reward_config({"collision_weight": 9.0}, "pointgoal")
    cfg = small_learn_config("pointgoal", temporal_cores=("gru/collision_weight=9",))
    with pytest.raises(ValueError, match="arm 'gru/collision_weight=9': pointgoal episodes do not read"):
        bench_learn(cfg, tmp_path / "out", "cpu", 32, tmp_path / "corpus", None, say=lambda m: None)
    assert not (tmp_path / "out").exists()


def test_runs_spread_over_gpus_round_robin() -> None:
    assert run_devices("cpu", 0, 3) == ["cpu"] * 3
    assert run_devices("cuda", 4, 6) == ["cuda:0", "cuda:1", "cuda:2", "cuda:3", "cuda:0", "cuda:1"]
    with pytest.raises(ValueError, match="CUDA"):
        run_devices("cpu", 2, 2)
    places = run_devices("cuda", 2, 5)
    lanes = gpu_lanes(5, 2)  # one process per GPU trains its lane's runs one after another
    assert lanes == [[0, 2, 4], [1, 3]]
    assert [{places[k] for k in lane} for lane in lanes] == [{"cuda:0"}, {"cuda:1"}]


def test_arms_run_seed_by_seed_and_name_their_engine_fields() -> None:
    cfg = LearnConfig(seeds=(0, 1), temporal_cores=("mamba2", "mamba2/attention=fused,patch_size=32"))
    assert run_order(cfg) == [
        ("mamba2", 0), ("mamba2/attention=fused,patch_size=32", 0),
        ("mamba2", 1), ("mamba2/attention=fused,patch_size=32", 1),
    ]  # fmt: skip
    assert parse_arm("gru") == ("gru", {}, {}, {}, {})
    assert parse_arm("mamba2/attention=fused,patch_size=32") == (
        "mamba2",
        {"attention": "fused", "patch_size": 32},
        {},
        {},
        {},
    )
    # A PPO setting goes to the arm's training alone, on top of the job's.
    bounded = parse_arm("mamba2/mean_bound_coef=1,patch_size=32")
    assert bounded.ppo == {"mean_bound_coef": 1.0} and bounded.engine == {"patch_size": 32}
    arm_spec = "mamba2/mean_bound_coef=1,ent_coef=0.01,lr=6e-4"
    job_cfg = LearnConfig(temporal_cores=("mamba2", arm_spec))
    plain = train_config(job_cfg, "mamba2", 0, torch.device("cpu"))
    tcfg = train_config(job_cfg, arm_spec, 0, torch.device("cpu"))
    assert (tcfg.ppo.mean_bound_coef, tcfg.ppo.ent_coef, tcfg.ppo.lr) == (1.0, 0.01, 6e-4)
    # The learning recipe's rate is the task's, chosen by resolve; the arm sets its own.
    assert plain.ppo.lr == TASK_RATE
    assert replace(tcfg.ppo, mean_bound_coef=0.0, ent_coef=plain.ppo.ent_coef, lr=plain.ppo.lr) == plain.ppo
    # A run size replaces the job's (here learning_size's on a CPU: 8 actors, 32-step rollouts) in that arm alone.
    wide = "mamba2/actors=16,rollout_length=8"
    assert parse_arm(wide).size == {"n_actors": 16, "rollout_length": 8}
    sized = LearnConfig(temporal_cores=("mamba2", wide))
    assert (train_config(sized, "mamba2", 0, torch.device("cpu")).n_actors, plain.rollout_length) == (8, 32)
    tsized = train_config(sized, wide, 0, torch.device("cpu"))
    assert (tsized.n_actors, tsized.rollout_length) == (16, 8)
    assert replace(tsized, n_actors=8, rollout_length=32) == plain
    # A RewardConfig weight goes to the arm's training env, on top of the job's --reward.
    arm = parse_arm("mamba2/collision_weight=9,patch_size=32")
    assert arm.engine == {"patch_size": 32} and arm.reward == {"collision_weight": 9.0}
    job = LearnConfig(reward=(("collision_weight", 6.0), ("exploration_weight", 0.25)))
    assert arm_reward(job, "mamba2/collision_weight=9") == {
        "collision_weight": 9.0,
        "exploration_weight": 0.25,
    }
    assert arm_reward(job, "mamba2") == {"collision_weight": 6.0, "exploration_weight": 0.25}
    for bad, why in (
        ("lstm", "unknown temporal core"),
        ("mamba2/", "KEY=VALUE"),
        ("mamba2/temporal_core=gru", "unknown field 'temporal_core'"),
        ("mamba2/colision_weight=9", "RewardConfig weight"),
        ("mamba2/collision_weight=high", "KEY=NUMBER"),
        ("mamba2/exploration_table_bits=12", "unknown reward weight"),
        ("mamba2/attention=flash", "attention expects one of"),
        ("mamba2/mean_bound_coef=strong", "mean_bound_coef expects a number"),
        ("mamba2/lr=0", "lr expects a positive learning rate"),
        ("mamba2/actors=0", "actors expects a positive whole number"),
        ("mamba2/rollout_length=6.5", "rollout_length expects a positive whole number"),
        ("mamba2/n_actors=16", r"or a run size \(actors, rollout_length\)"),
        ("mamba2/lr=-1e-4", "lr expects a positive learning rate"),
        ("mamba2/max_grad_norm=1", "unknown field 'max_grad_norm'"),
    ):
        with pytest.raises(ValueError, match=why):
            parse_arm(bad)


def test_bench_learn_cli_first_seed_picks_the_seeds(tmp_path: Path) -> None:
    """`--first-seed 2 --seeds 1` trains seed 2 only (one study spread over several jobs); `--engine`
    shapes every run's engine, and an `--arm`'s fields go on top of it for that arm's runs."""
    from typer.testing import CliRunner

    from navi.cli import build_app

    root = tmp_path / "corpora"
    build_default_corpus(root / "procedural-train-64", resolution=64, count=1, seed=0)
    build_default_corpus(root / "procedural-unseen-64", resolution=64, count=1, seed=1000)
    out = tmp_path / "out"
    args = "bench learn --seeds 1 --first-seed 2 --arm gru --arm gru/head_hidden=16,existential_tax=-1"
    args += " --budget-s 1 --eval-every-s 1 --reward existential_tax=-0.5 --reward exploration_weight=0.25"
    args += " --actors 4 --rollout-length 8 --eval-actors 4 --eval-steps 16 --eval-episode-steps 8"
    args += f" --resolution 64 --no-compile --device cpu --json --corpus-root {root} --out {out}"
    args += f" --openarena {tmp_path / 'none.pk3'} --engine head_hidden=24"
    result = CliRunner().invoke(build_app(), args.split())
    assert result.exit_code == 0, result.output
    saved = json.loads((out / "result.json").read_text())
    assert saved["config"]["seeds"] == [2]
    arm = "gru/head_hidden=16,existential_tax=-1"
    assert [(r["arm"], r["seed"]) for r in saved["runs"]] == [("gru", 2), (arm, 2)]
    assert [r["train_config"]["engine"]["head_hidden"] for r in saved["runs"]] == [24, 16]
    assert all(r["train_config"]["seed"] == 2 and r["temporal_core"] == "gru" for r in saved["runs"])
    # The arm's reward weight replaces the job's in its training env alone; the other weight stays.
    assert [r["reward_overrides"] for r in saved["runs"]] == [
        {"existential_tax": -0.5, "exploration_weight": 0.25},
        {"existential_tax": -1.0, "exploration_weight": 0.25},
    ]
    for run, tax in zip(saved["runs"], (-0.5, -1.0), strict=True):
        rows = (Path(run["checkpoint"]).parents[1] / "metrics" / "metrics.jsonl").read_text().splitlines()
        logged = [json.loads(row) for row in rows]  # every step of every actor paid the constant term
        assert logged and all(row["reward/existential_per_step"] == pytest.approx(tax) for row in logged)
    assert saved["reward"]["existential_tax"] == -0.5  # evaluations and baselines fly the job's reward
    assert list(saved["summary"]) == ["gru", arm]
    assert (out / "runs" / "gru-head_hidden=16-existential_tax=-1-seed2").is_dir()
    warm = saved["warmups"]  # the compile warm-up: once per arm, before every run and off their clocks
    assert [(w["arm"], w["updates"]) for w in warm] == [("gru", 3), (arm, 3)]
    assert (out / "runs" / "gru-head_hidden=16-existential_tax=-1-warmup-cpu").is_dir()
    assert (
        "Compile warm-up before the runs, outside their clocks: 3 untimed updates per arm"
        in (out / "report.md").read_text()
    )
    assert f"| {arm} | 1 |" in (out / "report.md").read_text()


def test_obstacle_collisions_are_measured_and_counted_among_collisions(tmp_path: Path) -> None:
    """`make_env(obstacles=K)` gives every actor K moving obstacles; evaluation reports the contacts with
    them as obstacle_collisions_per_1k, a part of collisions_per_1k (0 when there are no obstacles)."""
    from navi_learner.envs.factory import EnvUnavailable

    corpus = tmp_path / "c"
    build_default_corpus(corpus, resolution=64, count=1, seed=0)
    crowded = make_env(corpus, 8, "cpu", 3, episode_steps=20, obstacles=48)
    assert crowded.obstacles is not None and crowded.obstacles.count == 48  # type: ignore[attr-defined]
    counted = {"collision": 0, "obstacle_collision": 0}  # an independent count of what the env reported
    step = crowded.step

    def counting_step(action: torch.Tensor) -> StepLike:
        out = step(action)
        for key in counted:
            counted[key] += int(out.info[key].sum())
        return out

    crowded.step = counting_step  # type: ignore[method-assign,assignment]
    m = evaluate(crowded, RandomPolicy(seed=0), 120, seed=3)
    assert counted["obstacle_collision"] > 0, "no drone met an obstacle: the test exercised nothing"
    assert counted["obstacle_collision"] <= counted["collision"]  # an obstacle contact is a collision
    assert m.obstacle_collisions_per_1k == pytest.approx(1000.0 * counted["obstacle_collision"] / (120 * 8))
    assert m.collisions_per_1k == pytest.approx(1000.0 * counted["collision"] / (120 * 8))
    lo, hi = m.ci["obstacle_collisions_per_1k"]
    assert lo <= m.obstacle_collisions_per_1k <= hi
    plain = evaluate(make_env(corpus, 4, "cpu", 3, episode_steps=20), RandomPolicy(seed=0), 10, seed=3)
    assert plain.obstacle_collisions_per_1k == 0.0
    with pytest.raises(EnvUnavailable):
        make_env(corpus, 4, "cpu", 3, obstacles=65)


def test_training_stats_count_obstacle_collisions_among_collisions() -> None:
    from types import SimpleNamespace

    from navi_learner.ppo.stats import EpisodeStats

    stats = EpisodeStats(4, torch.device("cpu"))
    for step in range(10):
        collision = torch.tensor([True, step % 2 == 0, False, False])  # (4,)
        info = {
            "collision": collision,
            "obstacle_collision": collision & torch.tensor([False, True, False, False]),
        }
        out = SimpleNamespace(
            reward=torch.zeros(4), done=torch.zeros(4, dtype=torch.bool), truncated=torch.zeros(4, dtype=torch.bool),
            reward_terms={}, info=info,
        )  # fmt: skip
        stats.update(out)  # type: ignore[arg-type]
    row = stats.read()
    assert row["collisions_per_1k"] == pytest.approx(1000.0 * 15 / 40)
    assert row["obstacle_collisions_per_1k"] == pytest.approx(1000.0 * 5 / 40)


def test_procedural_share_repeats_the_procedural_train_scenes(tmp_path: Path) -> None:
    from navi_bench.learn import prepare_splits
    from navi_env.corpus.folder import read_manifest

    root = tmp_path / "corpora"
    build_default_corpus(root / "procedural-train-64", resolution=64, count=2, seed=0)
    build_default_corpus(root / "procedural-unseen-64", resolution=64, count=1, seed=1000)
    build_default_corpus(root / "openarena-train-64", resolution=64, count=3, seed=50)  # stands in for maps
    build_default_corpus(root / "openarena-unseen-64", resolution=64, count=1, seed=60)
    plain = prepare_splits(root, 64, "cpu", None, say=lambda _: None)
    assert len(read_manifest(plain.train).scenes) == 5 and not plain.notes
    mixed = prepare_splits(root, 64, "cpu", None, say=lambda _: None, procedural_share=0.5)
    scenes = read_manifest(mixed.train).scenes
    assert len(scenes) == 2 * 2 + 3  # round(0.5 * 3 / (0.5 * 2)) = 2 copies of the 2 procedural scenes
    procedural = {s.source for s in read_manifest(root / "procedural-train-64").scenes}
    assert sum(s.source in procedural for s in scenes) == 4
    assert any("2 times, 57%" in note for note in mixed.notes)
    with pytest.raises(ValueError, match="procedural_share"):
        prepare_splits(root, 64, "cpu", None, say=lambda _: None, procedural_share=1.0)
