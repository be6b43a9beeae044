"""The reference checkpoints shipped with Navi, and the CPU path of the main job that fine-tunes them.

The references (navi_learner/reference/mamba2.pt for explore, mamba2-pointgoal.pt for point-goal) were
made by Navi on a GPU; their JSONs name the command. The CPU path fine-tunes one and then flies it live on
the eight unseen procedural scenes (seed 1000, one of each family, at 512^3 as `navi run` builds them)
with the CPU protocol (48 actors x 500 steps, episodes of 250: 96 episodes), as its task flies
(ACTION_NOISE: explore sampled with its std, point-goal its mean action): its verdict must hold with the
intervals, paired over the same spawns, not only on the point estimates.
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_bench.learn import LearnConfig
from navi_bench.learn import train_config as bench_train_config
from navi_env.corpus.folder import build_default_corpus
from navi_env.corpus.openarena import openarena_maps, split_openarena
from navi_learner import config
from navi_learner.envs.factory import make_env
from navi_learner.evaluation.baselines import goal_seeker_for_env
from navi_learner.evaluation.competence import EvalProtocol
from navi_learner.evaluation.evaluate import (
    CheckpointPolicy,
    EvalMetrics,
    beats_supported,
    competent_supported,
    contact_line,
    evaluate,
)
from navi_learner.evaluation.main_job import (
    CORPUS_RESOLUTION,
    POINTGOAL_REFERENCE,
    REFERENCE,
    REFERENCES,
    UNSEEN_SCENES,
    UNSEEN_SEED,
    MainJobConfig,
    MainJobError,
    cuda_config,
    judge,
    main_job,
    real_map_corpus,
    write_evaluation,
)
from navi_learner.serving.checkpoint import load_checkpoint


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


@pytest.mark.parametrize("task", sorted(REFERENCES))
def test_reference_checkpoint_says_how_it_was_made(task: str) -> None:
    reference = REFERENCES[task]
    made = json.loads(reference.with_suffix(".json").read_text())
    ckpt = load_checkpoint(reference)
    assert made["command"].startswith("navi ") and "--device cuda" in made["command"]
    assert ("--task pointgoal" in made["command"]) == (task == "pointgoal")
    assert ckpt.meta.step_id == made["steps"] and ckpt.meta.training_source == "rl"
    assert ckpt.meta.parent_checkpoint is None and ckpt.meta.temporal_core == "mamba2"
    assert ckpt.meta.obs_shape == [3, 256, 48] and ckpt.optimizer is not None
    assert ckpt.meta.config.get("task", "explore") == task


def test_main_job_cpu_path_fine_tunes_the_reference_and_reports_live(
    unseen: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    train = tmp_path / "train"
    build_default_corpus(train, resolution=CORPUS_RESOLUTION, count=1, seed=0)
    job = MainJobConfig(train, unseen, tmp_path / "models", "cpu", cpu_steps=256)
    report = main_job(job)
    out = capsys.readouterr().out
    assert "path: CPU. Fine-tuning the explore reference checkpoint" in out and "--device cuda" in out
    result = json.loads((report.parent / "evaluation.json").read_text())
    assert result["path"] == "cpu"
    trained, rand, reactive = (EvalMetrics(**r) for r in result["results"])
    assert (
        trained.steps == 500 and trained.actors == 48 and trained.episodes == 96 and rand.policy == "random"
    )
    fine_tuned = load_checkpoint(job.models_dir / "latest.pt")
    assert fine_tuned.meta.parent_checkpoint == str(REFERENCE)
    assert fine_tuned.meta.step_id == load_checkpoint(REFERENCE).meta.step_id + 256
    assert result["beats"] == {
        "random": beats_supported(trained, rand),
        "reactive": beats_supported(trained, reactive),
    }
    assert_beats_both(trained, rand, reactive)
    assert result["beats"] == {"random": True, "reactive": True}
    # The win holds with the intervals: no collision across the interval, coverage ratio's paired
    # interval above the bar's 1.5.
    assert result["competent"] is True and competent_supported(trained, reactive)
    text = report.read_text()
    assert "vs reactive: beats it" in text and "Competent (" in text and "): yes." in text


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
    # `navi run --actors N` sizes the CUDA run and keeps the rest of the recipe.
    chosen = cuda_config(replace(job, n_actors=1024))
    assert chosen.n_actors == 1024 and replace(chosen, n_actors=ours.n_actors) == ours


def test_the_learning_run_takes_fewer_actors_on_a_gpu_too_small_for_its_size(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """8,192 actors on a GPU with room for them (or whose memory cannot be read here), 2,048 under
    SMALL_GPU_GIB, 8 on a CPU; a size the caller set is kept. The help of every command that takes the size
    names these numbers."""
    cuda = torch.device("cuda")
    memory: list[float | None] = [None]
    monkeypatch.setattr(config, "gpu_memory_gib", lambda device: memory[0])
    sizes = {}
    for gib in (None, 80.0, config.SMALL_GPU_GIB, 24.0):
        memory[0] = gib
        sized = config.learning_size(config.TrainConfig(), cuda)
        sizes[gib] = (sized.n_actors, sized.rollout_length)
    big, small = (config.LEARNING_ACTORS, 64), (config.SMALL_GPU_ACTORS, 64)
    assert sizes == {None: big, 80.0: big, config.SMALL_GPU_GIB: big, 24.0: small}
    own = config.learning_size(config.TrainConfig(n_actors=512, rollout_length=16), cuda)
    assert (own.n_actors, own.rollout_length) == (512, 16)
    cpu = config.learning_size(config.TrainConfig(), torch.device("cpu"))
    assert (cpu.n_actors, cpu.rollout_length) == (8, 32)
    named = (f"{config.LEARNING_ACTORS:,}", f"{config.SMALL_GPU_ACTORS:,}", f"{config.SMALL_GPU_GIB:g} GiB")
    runner = CliRunner()
    for command in (["run", "--help"], ["bench", "learn", "--help"], ["bench", "transfer", "--help"]):
        shown = runner.invoke(build_app(), command, env={"COLUMNS": "400"})
        assert shown.exit_code == 0, shown.output
        line = next(x for x in shown.output.splitlines() if "--actors" in x)
        assert all(n in line for n in named), (command, line)


def test_the_learning_recipe_trains_each_task_at_its_own_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    """The recipe's rate is TASK_RATE and resolve picks the task's (TASK_LR, looked up per run); a rate
    the run sets is kept, 0 among them (weights that do not move), an unknown task or another negative
    rate is named, and `navi train` keeps PPOConfig's own default."""
    recipe = config.learning_recipe()
    assert recipe.ppo.lr == config.TASK_RATE
    obs = (3, 256, 48)
    rates = {t: config.resolve(replace(recipe, task=t), obs).ppo.lr for t in ("explore", "pointgoal")}
    assert rates == {"explore": 6e-4, "pointgoal": 6e-4} == config.TASK_LR
    monkeypatch.setitem(config.TASK_LR, "pointgoal", 2e-4)  # rates that differ tell the tasks apart
    rates = {t: config.resolve(replace(recipe, task=t), obs).ppo.lr for t in ("explore", "pointgoal")}
    assert rates == {"explore": 6e-4, "pointgoal": 2e-4}
    for own_rate in (1e-4, 0.0):
        own = replace(recipe, task="pointgoal", ppo=replace(recipe.ppo, lr=own_rate))
        assert config.resolve(own, obs).ppo.lr == own_rate
    assert config.resolve(config.TrainConfig(), obs).ppo.lr == config.PPOConfig().lr == 5e-4
    with pytest.raises(ValueError, match=r"unknown task 'hover'.*explore, pointgoal"):
        config.resolve(replace(recipe, task="hover"), obs)
    with pytest.raises(ValueError, match=r"lr must be >= 0, or -1 for the task's rate; got -0.5"):
        config.resolve(replace(recipe, ppo=replace(recipe.ppo, lr=-0.5)), obs)


def test_main_job_point_goal_cpu_path_fine_tunes_its_reference_and_compares_with_the_seekers(
    unseen: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    train = tmp_path / "train"
    build_default_corpus(train, resolution=CORPUS_RESOLUTION, count=1, seed=0)
    # The job's plumbing for point-goal episodes, on a small evaluation (the CPU protocol's verdict is
    # the next test's).
    small = EvalProtocol(actors=8, steps=200, episode_steps=100)
    job = MainJobConfig(
        train, unseen, tmp_path / "models", "cpu", cpu_steps=256, task="pointgoal", protocol=small
    )
    assert cuda_config(job).task == "pointgoal" and job.reference_checkpoint() == POINTGOAL_REFERENCE
    report = main_job(job)
    assert "path: CPU. Fine-tuning the pointgoal reference checkpoint" in capsys.readouterr().out
    fine_tuned = load_checkpoint(job.models_dir / "latest.pt")
    assert fine_tuned.meta.parent_checkpoint == str(POINTGOAL_REFERENCE)
    assert fine_tuned.meta.config["task"] == "pointgoal"
    assert fine_tuned.meta.step_id == load_checkpoint(POINTGOAL_REFERENCE).meta.step_id + 256
    result = json.loads((report.parent / "evaluation.json").read_text())
    trained, rand, greedy, oracle = (EvalMetrics(**r) for r in result["results"])
    assert (rand.policy, greedy.policy, oracle.policy) == ("random", "greedy", "oracle")
    assert all(r.task == "pointgoal" for r in (trained, rand, greedy, oracle))
    assert greedy.success_rate > rand.success_rate
    # the verdicts are the trained drone's metrics against each seeker's, worked out here by hand
    for name, other in (("random", rand), ("greedy", greedy), ("oracle", oracle)):
        won = trained.success_rate > other.success_rate
        won = won and trained.collisions_per_episode <= other.collisions_per_episode
        assert result["beats"][name] is won, (name, trained, other)
        assert f"vs {name}: {'beats it' if won else 'does not beat it'}" in report.read_text()
    fewer = trained.collisions_per_episode < greedy.collisions_per_episode or (
        trained.collisions_per_episode == greedy.collisions_per_episode == 0.0
    )
    competent = trained.success_rate >= 0.9 and trained.spl >= 0.75 and fewer
    assert result["competent"] is competent
    assert f"fewer collisions per episode than greedy): {'yes' if competent else 'no'}." in report.read_text()


def test_point_goal_reference_flies_the_cpu_protocol_ahead_of_the_greedy_seeker(unseen: Path) -> None:
    """The shipped point-goal reference on the CPU path's point-goal protocol (48 actors x 1,000 steps,
    the task's own 500-step episodes, env seed 12345) on the eight unseen scenes: near the competence bar
    (success 0.92 measured there after the fine-tune, reference/README.md) and well ahead of the map-less
    greedy seeker in success, SPL and collisions per episode."""
    protocol = EvalProtocol.for_device(torch.device("cpu"), "pointgoal")
    assert (protocol.actors, protocol.steps, protocol.episode_steps) == (48, 1000, 500)
    env = make_env(
        unseen, protocol.actors, "cpu", protocol.seed, episode_steps=protocol.episode_steps, task="pointgoal"
    )
    reference = CheckpointPolicy(POINTGOAL_REFERENCE, torch.device("cpu"))
    trained = evaluate(env, reference, protocol.steps, protocol.seed)
    greedy = evaluate(env, goal_seeker_for_env("greedy", env), protocol.steps, protocol.seed)
    assert trained.episodes >= protocol.actors and greedy.episodes >= protocol.actors
    assert trained.success_rate >= 0.85 and trained.spl >= 0.75, trained
    assert trained.success_rate > greedy.success_rate + 0.1, (trained, greedy)
    assert trained.spl > greedy.spl and trained.collisions_per_episode < greedy.collisions_per_episode


def test_main_job_refuses_a_reference_of_another_task(tmp_path: Path) -> None:
    """The CPU path checks its reference before it builds anything."""
    train, unseen = tmp_path / "train", tmp_path / "unseen"
    job = MainJobConfig(train, unseen, tmp_path / "models", "cpu", task="pointgoal", reference=REFERENCE)
    with pytest.raises(MainJobError, match="trained for task 'explore', not 'pointgoal'"):
        main_job(job)
    assert not train.exists() and not unseen.exists()


OPENARENA_PK3 = Path(
    os.environ.get(
        "NAVI_OPENARENA_PK3", Path(__file__).resolve().parents[2] / "artifacts/data/openarena/pak1-maps.pk3"
    )
)


@pytest.mark.data
@pytest.mark.skipif(
    not OPENARENA_PK3.is_file(),
    reason=f"OpenArena maps pk3 not found at {OPENARENA_PK3} (run tests/data/fetch_openarena.sh or set NAVI_OPENARENA_PK3)",
)
def test_main_job_judges_the_drone_on_held_out_real_maps_in_a_section_of_their_own(
    unseen: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """With the OpenArena package present the job also flies the trained drone and the baselines on held-out
    maps (here the first of them) and labels that verdict as real maps; the procedural verdict stays as it is."""
    monkeypatch.chdir(tmp_path)
    train = tmp_path / "train"
    build_default_corpus(train, resolution=CORPUS_RESOLUTION, count=1, seed=0)
    small = EvalProtocol(actors=8, steps=120, episode_steps=60)
    job = MainJobConfig(
        train,
        unseen,
        tmp_path / "models",
        "cpu",
        cpu_steps=64,
        protocol=small,
        openarena=OPENARENA_PK3,
        real_maps=1,
    )
    report = main_job(job)
    out = capsys.readouterr().out
    result = json.loads((report.parent / "evaluation.json").read_text())
    real = result["real_maps"]
    held = split_openarena(openarena_maps(OPENARENA_PK3))[1][0]
    assert [
        s["name"] for s in json.loads((Path(real["corpus"]) / "manifest.json").read_text())["scenes"]
    ] == [Path(held).stem]
    rows = [EvalMetrics(**r) for r in real["results"]]
    assert [r.policy for r in rows][1:] == ["random", "reactive"] and rows[0].policy.startswith("trained (")
    assert all(r.steps == 120 and r.actors == 8 for r in rows)
    assert rows != [EvalMetrics(**r) for r in result["results"]]  # other scenes, other flights
    verdict, beats, competence = judge("explore", rows)
    assert real["beats"] == beats and real["competent"] is competence
    text = report.read_text()
    assert (
        "## Real maps never seen: the held-out OpenArena maps" in text and f"On real maps: {verdict}" in text
    )
    assert f"[navi run] on real maps never seen ({real['corpus']}): {verdict}" in out
    contacts = contact_line(rows[0])  # how few drones made the contacts, where the drone touched anything
    section = text.split("## Real maps never seen", 1)[1]
    assert (
        (contacts in section and f"[navi run] {contacts}" in out) if contacts else "Contacts (" not in section
    )
    # without the package the job says where to get it and judges on procedural scenes alone
    missing = replace(job, openarena=tmp_path / "absent.pk3", models_dir=tmp_path / "models2")
    report = main_job(missing)
    assert "no verdict on real maps" in capsys.readouterr().out
    assert "real_maps" not in json.loads((report.parent / "evaluation.json").read_text())


def test_the_job_says_how_few_drones_made_the_contacts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Under each verdict the job names how the trained drone's contact steps spread over its actors: the
    stored collision A/B's seed 2 on the held-out maps, where one drone of 256 made 479 of the 507."""
    stored = Path(__file__).resolve().parents[2] / "benchmarks/results/learn-collision-2026-12-01-H200"
    result = json.loads((stored / "result.json").read_text())
    base = result["baselines"]["openarena"]
    run = next(r for r in result["runs"] if r["seed"] == 2)
    rows = [EvalMetrics(**m) for m in (run["final_by_split"]["openarena"], base["random"], base["reactive"])]
    job = MainJobConfig(tmp_path / "train", tmp_path / "unseen", tmp_path / "models", "cuda")
    protocol = EvalProtocol(actors=256, steps=1000, episode_steps=500)
    line = "Contacts (trained): 9 of 256 actors touched a surface; the 3 busiest made 491 of the 507 contact steps"
    report = write_evaluation(tmp_path, job, protocol, rows, None, "CUDA", (tmp_path / "held", rows))
    text, out = report.read_text(), capsys.readouterr().out
    unseen_part, real_part = text.split("## Real maps never seen", 1)
    assert line in unseen_part and line in real_part
    assert out.count(f"[navi run] {line} (one actor 479).") == 2
    quiet = [replace(rows[0], per_actor={**rows[0].per_actor, "collision": [0.0] * 256}), *rows[1:]]
    report = write_evaluation(tmp_path, job, protocol, quiet, None, "CUDA")
    assert "Contacts (" not in report.read_text() and "Contacts (" not in capsys.readouterr().out


@pytest.mark.data
@pytest.mark.skipif(
    not OPENARENA_PK3.is_file(),
    reason=f"OpenArena maps pk3 not found at {OPENARENA_PK3} (run tests/data/fetch_openarena.sh or set NAVI_OPENARENA_PK3)",
)
def test_main_job_rebuilds_real_maps_compiled_under_older_fit_rules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The held-out real maps are built once and reused; a folder whose manifest predates the compiler's
    cube rules (no fit_rules) is rebuilt, and says so. (At 64³ here, for time.)"""
    import navi_learner.evaluation.main_job as main_job_module

    monkeypatch.setattr(main_job_module, "CORPUS_RESOLUTION", 64)
    job = MainJobConfig(
        tmp_path / "train",
        tmp_path / "unseen",
        tmp_path / "models",
        "cpu",
        openarena=OPENARENA_PK3,
        real_maps=1,
    )
    folder = real_map_corpus(job, torch.device("cpu"))
    assert folder is not None and "building 1 held-out OpenArena maps" in capsys.readouterr().out
    manifest = folder / "manifest.json"
    first = json.loads(manifest.read_text())
    assert real_map_corpus(job, torch.device("cpu")) == folder
    assert "OpenArena" not in capsys.readouterr().out and json.loads(manifest.read_text()) == first
    del first["fit_rules"]
    manifest.write_text(json.dumps(first))
    assert real_map_corpus(job, torch.device("cpu")) == folder
    assert "rebuilding (cubes fitted under older compiler rules)" in capsys.readouterr().out
    assert "fit_rules" in json.loads(manifest.read_text())
