"""`navi run`: the main job. It ends with a table where the trained drone is compared, live, with the
random and reactive baselines on procedural scenes it never trained on.

On CUDA: build the procedural default corpus and an unseen one when missing, train (resuming from the
registry's latest when compatible) until the drone is competent on the unseen scenes or the time
budget ends, with a progress bar that shows the latest unseen collisions and coverage; promote; then
evaluate with enough steps for episodes to finish, and write the table and the learning curves.

On a CPU, where minutes cannot train this engine from scratch: start from the task's reference
checkpoint shipped with Navi (made by `navi run` on a GPU; reference/README.md and its JSONs say how),
fine-tune it for the CPU budget on the default corpus, then evaluate the same way.

With task "pointgoal" the job trains point-goal episodes (on CUDA from scratch until the point-goal bar,
docs/TASKS.md, or the budget; on a CPU from the point-goal reference) and compares with random, greedy
and oracle.

Where the OpenArena maps are on the machine (navi_env.corpus.openarena), the job also flies the trained
drone and the baselines on the held-out fifth of them, maps no drone Navi trains has seen, and reports
that verdict in a section of its own, labelled real maps.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from navi_learner.config import (
    EngineConfig,
    PPOConfig,
    RunBudget,
    TrainConfig,
    learning_recipe,
    learning_size,
)
from navi_learner.envs.factory import EnvUnavailable, corpus_summary, make_env
from navi_learner.evaluation.competence import CompetenceMonitor, EvalProtocol, baseline_policies, plot_curves
from navi_learner.evaluation.evaluate import (
    COLLISION_FLOOR_PER_1K,
    CheckpointPolicy,
    EvalMetrics,
    beats_supported,
    collision_bar,
    comparison_table,
    competent_supported,
    contact_line,
    evaluate,
    flown_by,
    goal_competent,
    jsonable,
    paired_intervals,
)
from navi_learner.ppo.train import train
from navi_learner.serving.checkpoint import CheckpointError, CheckpointMeta, atomic_write, read_meta
from navi_learner.serving.references import REFERENCES
from navi_learner.serving.registry import ModelRegistry

REFERENCE = REFERENCES["explore"]
"""The explore reference checkpoint the CPU path fine-tunes (reference/mamba2.json: how it was made)."""

POINTGOAL_REFERENCE = REFERENCES["pointgoal"]
"""The point-goal reference checkpoint the CPU path fine-tunes (its JSON: how it was made)."""

UNSEEN_SEED = 1000
"""Seed of the procedural scenes the main job evaluates on (the default corpus uses seed 0)."""

UNSEEN_SCENES = 8
"""Unseen scenes: the first eight default entries, one each of rooms, corridors, hall, maze, caves, forest,
building and yard, as in `navi bench learn`'s procedural-unseen split. Arenas, platforms and the scaled
open entries are judged by `navi bench transfer`, whose unseen procedural part holds every family."""

CPU_TRAIN_SCENES = 4
"""Scenes of the default corpus the CPU path builds and fine-tunes on (16 on CUDA)."""

CORPUS_RESOLUTION = 512
"""Cells per cube edge of the main job's scenes on both paths: the reference checkpoint was trained at
512^3, and a policy flies differently through the blockier geometry of coarser scenes."""


class MainJobError(RuntimeError):
    """A piece the main job needs is missing."""


@dataclass(frozen=True)
class MainJobConfig(RunBudget):
    """`navi run` options: the corpora, device and task, and the run budget (RunBudget's fields)."""

    corpus: Path
    unseen: Path
    models_dir: Path
    device: str
    seed: int = 0
    reference: Path | None = None
    """The checkpoint the CPU path fine-tunes; None: the task's (REFERENCES)."""
    task: str = "explore"
    """explore, or pointgoal."""
    protocol: EvalProtocol | None = None
    """The unseen evaluation; None: EvalProtocol.for_device (a smaller one only where a test says why)."""
    openarena: Path | None = None
    """The OpenArena package; where it exists, the job also judges the drone on its held-out maps."""
    real_maps: int = 0
    """How many of the held-out maps that verdict flies (0: all ten)."""

    def reference_checkpoint(self) -> Path:
        """The checkpoint the CPU path fine-tunes."""
        return self.reference or REFERENCES[self.task]


def real_map_corpus(job: MainJobConfig, device: torch.device) -> Path | None:
    """The corpus of the held-out OpenArena maps at CORPUS_RESOLUTION beside the unseen corpus (built when
    missing), or None without the package (and a line that says where to get it)."""
    if job.openarena is None:
        return None
    if not job.openarena.is_file():
        print(
            f"[navi run] no OpenArena maps at {job.openarena} (tests/data/fetch_openarena.sh fetches them): "
            "no verdict on real maps",
            flush=True,
        )
        return None
    from navi_env.corpus.folder import build_corpus, corpus_is_current
    from navi_env.corpus.openarena import openarena_maps, split_openarena

    held = split_openarena(openarena_maps(job.openarena))[1][: job.real_maps or None]
    folder = job.unseen.parent / f"openarena-held-out-{len(held)}-{CORPUS_RESOLUTION}"
    if not corpus_is_current(folder):
        what = (
            "rebuilding (cubes fitted under older compiler rules)"
            if (folder / "manifest.json").is_file()
            else "building"
        )
        print(
            f"[navi run] {what} {len(held)} held-out OpenArena maps ({CORPUS_RESOLUTION}^3) into {folder}",
            flush=True,
        )
        build_corpus(
            [f"{job.openarena}:{m}" for m in held],
            folder,
            CORPUS_RESOLUTION,
            device,
            progress=lambda line: print(f"[navi run] {line}", flush=True),
        )
    return folder


def ensure_corpus(corpus: Path, device: torch.device, seed: int = 0, count: int = 16) -> None:
    """Build `count` procedural scenes of `seed` at 512^3 into `corpus` unless it already has a
    manifest (8 scenes of 512^3 take about 75 s on 2 CPU cores; the GPU builds them in seconds)."""
    if (corpus / "manifest.json").is_file():
        return
    try:
        from navi_env.corpus.folder import CorpusError, build_default_corpus
    except ImportError as err:
        raise MainJobError(
            f"no corpus at {corpus} and navi_env's corpus builder is not importable ({err})"
        ) from err
    resolution = CORPUS_RESOLUTION
    print(
        f"[navi run] building procedural scenes of seed {seed} ({count} scenes, {resolution}^3) into {corpus}",
        flush=True,
    )
    try:
        build_default_corpus(
            corpus,
            resolution=resolution,
            count=count,
            seed=seed,
            device=device,
            progress=lambda line: print(f"[navi run] {line}", flush=True),
        )
    except CorpusError as err:
        raise MainJobError(f"building the corpus {corpus} failed: {err}") from err


def cuda_config(job: MainJobConfig) -> TrainConfig:
    """Training on a GPU: the learning benchmark's run (config.learning_recipe at learning_size's 8,192
    actors, or the job's `n_actors`, and 64-step rollouts), time-limited by the job's budget."""
    return replace(
        learning_size(replace(learning_recipe(), n_actors=job.n_actors), torch.device(job.device)),
        time_limit_s=job.budget_s,
        seed=job.seed,
        device=job.device,
        task=job.task,
    )


CPU_LR = 1e-5
"""The CPU fine-tune's learning rate. 2,048 steps of 4 actors teach the reference nothing new; the step
shows the training loop and the registry on a CPU. At 1e-4 its noisy updates cost the reference its
safety on the unseen scenes (2.29 collisions per 1k [0, 6.88] against 0)."""


def cpu_config(job: MainJobConfig, start_step: int) -> TrainConfig:
    """Fine-tuning on a CPU: 4 actors, 64-step rollouts, CPU_LR, job.cpu_steps steps."""
    return TrainConfig(
        n_actors=4,
        rollout_length=64,
        total_steps=start_step + job.cpu_steps,
        seed=job.seed,
        device=job.device,
        ppo=PPOConfig(lr=CPU_LR),
    )


def resume_point(registry: ModelRegistry, cfg: TrainConfig) -> tuple[Path | None, TrainConfig]:
    """The registry's latest when it uses the same temporal core and task (its engine shape comes along)."""
    if not registry.latest_path.is_file():
        return None, cfg
    try:
        meta = read_meta(registry.latest_path)
    except CheckpointError as err:
        print(f"[navi run] ignoring {registry.latest_path}: {err}", flush=True)
        return None, cfg
    if meta.temporal_core != cfg.engine.temporal_core or meta.config.get("task", "explore") != cfg.task:
        return None, cfg
    budget = cfg.total_steps if cfg.total_steps >= 10**12 else meta.step_id + cfg.total_steps
    return registry.latest_path, replace(
        cfg, engine=EngineConfig.from_dict(meta.config["engine"]), total_steps=budget
    )


def checked_reference(job: MainJobConfig) -> tuple[Path, CheckpointMeta]:
    """The CPU path's reference checkpoint and its metadata; MainJobError when it is missing or was
    trained for another task."""
    reference = job.reference_checkpoint()
    if not reference.is_file():
        raise MainJobError(f"the reference checkpoint {reference} is missing (it ships with Navi)")
    meta = read_meta(reference)
    trained_for = meta.config.get("task", "explore")
    if trained_for != job.task:
        raise MainJobError(
            f"the reference checkpoint {reference} was trained for task {trained_for!r}, not {job.task!r}"
        )
    return reference, meta


def main_job(job: MainJobConfig) -> Path:
    """Returns the path of the evaluation report."""
    dev = torch.device(job.device)
    cuda = dev.type == "cuda"
    reference = None if cuda else checked_reference(job)  # before any corpus is built
    ensure_corpus(job.corpus, dev, count=16 if dev.type == "cuda" else CPU_TRAIN_SCENES)
    ensure_corpus(job.unseen, dev, seed=UNSEEN_SEED, count=UNSEEN_SCENES)
    protocol = job.protocol or EvalProtocol.for_device(dev, job.task)
    registry = ModelRegistry(job.models_dir)
    try:
        unseen_env = make_env(
            job.unseen, protocol.actors, job.device, protocol.seed, episode_steps=protocol.episode_steps,
            task=job.task,
        )  # fmt: skip
    except EnvUnavailable as err:
        raise MainJobError(str(err)) from err
    monitor: CompetenceMonitor | None = None
    if cuda:
        cfg = cuda_config(job)
        resume, cfg = resume_point(registry, cfg)
        print(
            f"[navi run] path: CUDA. Training {'from ' + str(resume) if resume else 'from scratch'} on {job.corpus} "
            f"with {cfg.n_actors} actors until competent on the unseen scenes {job.unseen} or {job.budget_s:.0f} s",
            flush=True,
        )
        monitor = CompetenceMonitor(
            unseen_env,
            protocol,
            job.eval_every_s,
            say=lambda line: print(f"\n[navi run] {line}", flush=True),
            supported=True,  # stop where the final verdict, with its intervals, says competent
        )
    else:
        assert reference is not None
        resume, meta = reference
        made_by = json.loads(resume.with_suffix(".json").read_text()).get("command", "?")
        cfg = replace(
            cpu_config(job, meta.step_id), engine=EngineConfig.from_dict(meta.config["engine"]), task=job.task
        )
        print(
            f"[navi run] path: CPU. Fine-tuning the {job.task} reference checkpoint {resume} "
            f"(step {meta.step_id:,}, made on a GPU by `{made_by}`) for {job.cpu_steps:,} steps on {job.corpus}",
            flush=True,
        )
    try:
        env = make_env(job.corpus, cfg.n_actors, job.device, job.seed, task=job.task)
    except EnvUnavailable as err:
        raise MainJobError(str(err)) from err
    result = train(
        env,
        cfg,
        resume_from=resume,
        registry=registry,
        corpus_summary=corpus_summary(job.corpus, "sdfdag"),
        progress=None,
        monitor=monitor,
    )
    print(
        f"[navi run] trained to step {result.step_id:,} in {result.last_metrics.get('train_s', 0.0):.0f} s; "
        f"promoted: {result.promoted or 'no (did not beat the best)'}",
        flush=True,
    )
    trained = CheckpointPolicy(result.final_checkpoint, dev, seed=protocol.seed)
    trained.name = f"trained ({result.run_id})"
    baselines = baseline_policies(unseen_env, protocol)
    rows = [
        evaluate(unseen_env, p, protocol.steps, protocol.seed, progress=True) for p in (trained, *baselines)
    ]
    real: tuple[Path, list[EvalMetrics]] | None = None
    real_corpus = real_map_corpus(job, dev)
    if real_corpus is not None:
        real_env = make_env(
            real_corpus, protocol.actors, job.device, protocol.seed, episode_steps=protocol.episode_steps,
            task=job.task,
        )  # fmt: skip
        policies = (trained, *baseline_policies(real_env, protocol))
        real = (
            real_corpus,
            [evaluate(real_env, p, protocol.steps, protocol.seed, progress=True) for p in policies],
        )
    return write_evaluation(
        result.run_dir / "reports", job, protocol, rows, monitor, "cuda" if cuda else "cpu", real
    )


def judge(task: str, rows: list[EvalMetrics]) -> tuple[str, dict[str, bool], bool]:
    """The verdict line, which baselines the trained drone beats, and whether it is competent. `rows`: the
    trained policy, then random and reactive (explore) or random, greedy and oracle (point-goal)."""
    if task == "pointgoal":
        trained, rand, greedy, oracle = rows
        competence = goal_competent(trained, greedy)
        beats = {
            name: trained.success_rate > other.success_rate
            and trained.collisions_per_episode <= other.collisions_per_episode
            for name, other in (("random", rand), ("greedy", greedy), ("oracle", oracle))
        }
        versus = "; ".join(
            f"vs {name}: {'beats it' if won else 'does not beat it'}" for name, won in beats.items()
        )
        verdict = (
            f"Trained {versus} (a higher success rate, no more collisions per episode). Competent (success >= 0.9, "
            f"SPL >= 0.75, fewer collisions per episode than greedy): {'yes' if competence else 'no'}."
        )
        return verdict, beats, competence
    trained, rand, reactive = rows
    paired = {
        name: paired_intervals(trained, other) for name, other in (("random", rand), ("reactive", reactive))
    }
    beats = {"random": beats_supported(trained, rand), "reactive": beats_supported(trained, reactive)}
    bar = collision_bar(reactive)
    ratio = paired["reactive"]["coverage_ratio"]
    competence = competent_supported(trained, reactive)
    versus = "; ".join(
        f"vs {name}: {'beats it' if beats[name] else 'does not beat it'} (coverage ratio "
        f"[{paired[name]['coverage_ratio'][0]:.2f}, {paired[name]['coverage_ratio'][1]:.2f}], extra collisions "
        f"per 1k [{paired[name]['collision_difference'][0]:.2f}, {paired[name]['collision_difference'][1]:.2f}])"
        for name in ("random", "reactive")
    )
    verdict = (
        f"Trained {versus}. The verdicts use 95% intervals, paired over the same actors and spawns: beating "
        f"a pilot needs the coverage ratio's interval above 1 and at most {COLLISION_FLOOR_PER_1K} extra "
        f"collisions per 1k at its top. Competent (collisions within {bar:.3g} per 1k, half the reactive's or "
        f"{COLLISION_FLOOR_PER_1K} where it has none, and 1.5x its coverage, both across the interval: "
        f"collisions [{trained.ci['collisions_per_1k'][0]:.3g}, {trained.ci['collisions_per_1k'][1]:.3g}], "
        f"coverage ratio [{ratio[0]:.2f}, {ratio[1]:.2f}]): {'yes' if competence else 'no'}."
    )
    return verdict, beats, competence


def write_evaluation(
    reports: Path,
    job: MainJobConfig,
    protocol: EvalProtocol,
    rows: list[EvalMetrics],
    monitor: CompetenceMonitor | None,
    path_taken: str,
    real: tuple[Path, list[EvalMetrics]] | None = None,
) -> Path:
    """evaluation.md / .json (and on CUDA the learning curves) in the run's reports folder. `rows`: the
    trained policy, then random and reactive (explore) or random, greedy and oracle (point-goal); `real`:
    the held-out OpenArena corpus and the same policies' rows there, reported in a section of its own."""
    verdict, beats, competence = judge(job.task, rows)
    table = comparison_table(rows)
    contacts = contact_line(rows[0])  # "" where the drone touched nothing
    text = (
        f"# navi run: evaluation on unseen scenes ({path_taken} path, task {job.task})\n\n"
        f"{protocol.actors} actors x {protocol.steps} steps on {job.unseen} (procedural seed {UNSEEN_SEED}), "
        f"episodes of {protocol.episode_steps} steps, env seed {protocol.seed}, {flown_by(job.task)}; "
        f"95% bootstrap intervals over actors.\n\n{table}\n\n{verdict}\n"
        + (f"\n{contacts}\n" if contacts else "")
    )
    payload: dict[str, object] = {
        "path": path_taken,
        "protocol": asdict(protocol),
        "results": [asdict(r) for r in rows],
        "beats": beats,
        "competent": competence,
    }
    real_lines: list[str] = []
    if real is not None:
        corpus, real_rows = real
        real_verdict, real_beats, real_competence = judge(job.task, real_rows)
        real_table = comparison_table(real_rows)
        real_contacts = contact_line(real_rows[0])
        text += (
            f"\n## Real maps never seen: the held-out OpenArena maps\n\n"
            f"The same protocol on {corpus}: the fifth of the OpenArena maps that no training split holds "
            f"(navi_env.corpus.openarena), Quake 3 arenas unlike the procedural scenes.\n\n"
            f"{real_table}\n\nOn real maps: {real_verdict}\n"
            + (f"\n{real_contacts}\n" if real_contacts else "")
        )
        payload["real_maps"] = {
            "corpus": str(corpus),
            "results": [asdict(r) for r in real_rows],
            "beats": real_beats,
            "competent": real_competence,
        }
        real_lines = [real_table, f"[navi run] on real maps never seen ({corpus}): {real_verdict}"]
        real_lines += [f"[navi run] {real_contacts}"] if real_contacts else []
    if monitor is not None:
        payload["learning"] = monitor.to_json()
        why_not = plot_curves({"trained": monitor.curve}, monitor.baselines, reports / "learning_curves.png")
        text += "\n" + (
            f"Learning curves not drawn: {why_not}\n"
            if why_not
            else "![learning curves](learning_curves.png)\n"
        )
    atomic_write(reports / "evaluation.md", lambda f: f.write(text.encode()))
    blob = json.dumps(jsonable(payload), indent=1).encode()
    atomic_write(reports / "evaluation.json", lambda f: f.write(blob))
    print(table, flush=True)
    print(f"[navi run] {verdict}", flush=True)
    if contacts:
        print(f"[navi run] {contacts}", flush=True)
    for line in real_lines:
        print(line, flush=True)
    print(f"[navi run] evaluation: {reports / 'evaluation.md'}", flush=True)
    return reports / "evaluation.md"
