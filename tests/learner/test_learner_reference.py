"""The reference checkpoint shipped with Navi, and the CPU path of the main job that fine-tunes it.

The reference (navi_learner/reference/mamba2.pt) was made by Navi on a GPU; its JSON names the
command. Evaluated live here on the eight unseen procedural scenes (seed 1000, one of each family, at
512^3 as `navi run` builds them), deterministic actions, the CPU protocol (16 actors x 400 steps,
episodes of 200), it must collide no more than reactive (both usually 0: nothing to beat there) and
less than random, and cover more ground than both.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from navi_env.corpus.folder import build_default_corpus
from navi_learner.envs.factory import make_env
from navi_learner.evaluation.baselines import RandomPolicy, reactive_for_env
from navi_learner.evaluation.bench_learn import LearnConfig
from navi_learner.evaluation.bench_learn import train_config as bench_train_config
from navi_learner.evaluation.competence import EvalProtocol
from navi_learner.evaluation.evaluate import CheckpointPolicy, EvalMetrics, evaluate
from navi_learner.evaluation.main_job import (
    CORPUS_RESOLUTION,
    REFERENCE,
    UNSEEN_SCENES,
    UNSEEN_SEED,
    MainJobConfig,
    cuda_config,
    main_job,
)
from navi_learner.serving.checkpoint import load_checkpoint

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def unseen(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The main job's unseen corpus: procedural seed 1000, 8 scenes at 512^3 (about 75 s on 2 cores)."""
    folder = tmp_path_factory.mktemp("corpus") / "unseen"
    build_default_corpus(folder, resolution=CORPUS_RESOLUTION, count=UNSEEN_SCENES, seed=UNSEEN_SEED)
    return folder


def assert_beats_both(trained: EvalMetrics, rand: EvalMetrics, reactive: EvalMetrics) -> None:
    assert trained.collisions_per_1k < rand.collisions_per_1k, (trained, rand)
    assert trained.collisions_per_1k <= reactive.collisions_per_1k, (trained, reactive)
    assert trained.coverage_per_1k > rand.coverage_per_1k, (trained, rand)
    assert trained.coverage_per_1k > reactive.coverage_per_1k, (trained, reactive)


def test_reference_checkpoint_says_how_it_was_made() -> None:
    made = json.loads(REFERENCE.with_suffix(".json").read_text())
    ckpt = load_checkpoint(REFERENCE)
    assert made["command"].startswith("navi ") and "--device cuda" in made["command"]
    assert ckpt.meta.step_id == made["steps"] and ckpt.meta.training_source == "rl"
    assert ckpt.meta.parent_checkpoint is None and ckpt.meta.temporal_core == "mamba2"
    assert ckpt.meta.obs_shape == [3, 256, 48] and ckpt.optimizer is not None


def test_reference_beats_random_and_reactive_on_unseen_scenes(unseen: Path) -> None:
    protocol = EvalProtocol.for_device(CPU)
    rows = []
    for make in (
        lambda env: CheckpointPolicy(REFERENCE, CPU),
        lambda env: RandomPolicy(protocol.seed),
        reactive_for_env,
    ):
        env = make_env(unseen, protocol.actors, "cpu", protocol.seed, episode_steps=protocol.episode_steps)
        rows.append(evaluate(env, make(env), protocol.steps, protocol.seed))
    assert_beats_both(*rows)
    assert all(r.episodes > 0 for r in rows)  # returns are those of finished episodes


def test_main_job_cpu_path_fine_tunes_the_reference_and_reports_live(
    unseen: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    train = tmp_path / "train"
    build_default_corpus(train, resolution=CORPUS_RESOLUTION, count=1, seed=0)
    job = MainJobConfig(train, unseen, tmp_path / "models", "cpu", cpu_steps=256)
    report = main_job(job)
    out = capsys.readouterr().out
    assert "path: CPU. Fine-tuning the reference checkpoint" in out and "--device cuda" in out
    result = json.loads((report.parent / "evaluation.json").read_text())
    assert result["path"] == "cpu"
    trained, rand, reactive = (EvalMetrics(**r) for r in result["results"])
    assert trained.steps == 400 and trained.actors == 16 and rand.policy == "random"
    fine_tuned = load_checkpoint(job.models_dir / "latest.pt")
    assert fine_tuned.meta.parent_checkpoint == str(REFERENCE)
    assert fine_tuned.meta.step_id == load_checkpoint(REFERENCE).meta.step_id + 256
    assert result["beats"] == {
        "random": trained.collisions_per_1k <= rand.collisions_per_1k
        and trained.coverage_per_1k > rand.coverage_per_1k,
        "reactive": trained.collisions_per_1k <= reactive.collisions_per_1k
        and trained.coverage_per_1k > reactive.coverage_per_1k,
    }
    assert_beats_both(trained, rand, reactive)
    assert "vs reactive: beats it" in report.read_text()


def test_main_job_trains_on_a_gpu_with_the_learning_benchmarks_settings(tmp_path: Path) -> None:
    """`navi run` on CUDA is the measured `navi bench learn` run: same actors, rollout, PPO settings
    (the benchmark pins its own minibatch size, so a change of the PPO default leaves both alike)."""
    job = MainJobConfig(corpus=tmp_path, unseen=tmp_path, models_dir=tmp_path, device="cuda", budget_s=99.0)
    ours = cuda_config(job)
    bench = bench_train_config(LearnConfig(), "mamba2", job.seed, torch.device("cuda"))
    assert ours.ppo == bench.ppo
    assert (ours.n_actors, ours.rollout_length, ours.engine) == (
        bench.n_actors,
        bench.rollout_length,
        bench.engine,
    )
    assert ours.time_limit_s == job.budget_s


def test_main_job_point_goal_cpu_path_trains_from_scratch_and_compares_with_the_seekers(
    unseen: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    train = tmp_path / "train"
    build_default_corpus(train, resolution=CORPUS_RESOLUTION, count=1, seed=0)
    job = MainJobConfig(train, unseen, tmp_path / "models", "cpu", cpu_steps=256, task="pointgoal")
    assert cuda_config(job).task == "pointgoal"
    report = main_job(job)
    assert "Training point-goal episodes from scratch" in capsys.readouterr().out
    result = json.loads((report.parent / "evaluation.json").read_text())
    trained, rand, greedy, oracle = (EvalMetrics(**r) for r in result["results"])
    assert (rand.policy, greedy.policy, oracle.policy) == ("random", "greedy", "oracle")
    assert all(r.task == "pointgoal" for r in (trained, rand, greedy, oracle))
    assert set(result["beats"]) == {"random", "greedy", "oracle"}
    assert greedy.success_rate > rand.success_rate and "Competent (success >= 0.9" in report.read_text()
    made = load_checkpoint(job.models_dir / "latest.pt")
    assert made.meta.parent_checkpoint is None and made.meta.config["task"] == "pointgoal"
