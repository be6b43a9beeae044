"""`navi bench learn`: does the engine learn to fly scenes it never saw, and how fast?

Protocol (docs/TRAINING.md, "The learning benchmark"):
- Splits: train = procedural scenes of seed 0 + the OpenArena maps not held out; unseen = procedural
  scenes of seed 1000 + every fifth OpenArena map (sorted by name, starting with the first). The
  split, with every scene name, is written into the result. Without the OpenArena package the
  OpenArena parts are left out and the result says why.
- Arms: a temporal core, optionally followed by `/KEY=VALUE[,KEY=VALUE...]`: EngineConfig fields the
  arm's fresh engine replaces (`mamba2/attention=fused`) and RewardConfig weights its training env
  replaces on top of the job's (`mamba2/collision_weight=9`; evaluations and baselines fly the job's
  reward, and the collisions and coverage they count do not read it). The runs go seed by seed, every
  arm of a seed before the next seed, so that arms compared in one job share its conditions.
- For every arm and seed: train from scratch on the train split; every `eval_every_s`
  seconds of training evaluate the live policy, flown as its task is (ACTION_NOISE), on the unseen split
  (EvalProtocol) and record a curve point; stop at competence (at most half the reactive baseline's collisions per
  1,000 steps and at least 1.5x its coverage) or at the time budget.
- Report per run the training time and env steps to competence (null if never), the final metrics
  per unseen part with 95% bootstrap intervals, and per arm the median over all its seeds (a seed that
  never got there counts as beyond the budget: censored_median).
- With `nproc` > 1 every run trains data-parallel (DD-PPO, ppo/dist.py) on that many ranks through
  torchrun, `actors` per rank, each rank on every train scene; rank 0 runs the monitor and
  the final evaluation (run_ranks, rank_main), and its clock is the run's training time.
Output folder: result.json, curves.json, learning_curves.png, report.md.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import pickle
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, NamedTuple

import torch

from navi_env.corpus.openarena import openarena_maps, split_openarena
from navi_learner.config import (
    TEMPORAL_CORES,
    EngineConfig,
    TemporalCoreName,
    TrainConfig,
    engine_overrides,
    learning_recipe,
    learning_size,
)
from navi_learner.envs.factory import corpus_summary, make_env, parse_reward_overrides, reward_config
from navi_learner.evaluation.competence import (
    CompetenceMonitor,
    EvalProtocol,
    evaluate_baselines,
    plot_curves,
)
from navi_learner.evaluation.evaluate import EvalMetrics, comparison_table, contact_line, jsonable
from navi_learner.ppo import dist as ddp
from navi_learner.ppo.dist import Dist

Say = Callable[[str], None]


def say_stderr(line: str) -> None:
    """Progress lines of a run (its evaluations) on stderr, so that stdout carries results only."""
    print(line, file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Splits:
    """Corpus folders of the benchmark and what is in them."""

    train: Path
    unseen: Path
    unseen_parts: dict[str, Path]
    scenes: dict[str, list[str]]
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class LearnConfig:
    """One `navi bench learn` job."""

    seeds: tuple[int, ...] = (0, 1, 2)
    temporal_cores: tuple[str, ...] = ("mamba2",)
    """The arms: a temporal core each, optionally `CORE/KEY=VALUE[,KEY=VALUE...]` (parse_arm)."""
    time_budget_s: float = 600.0
    """Training seconds per run (evaluations excluded)."""
    eval_every_s: float = 30.0
    """Training seconds between two evaluations on the unseen split."""
    stop_at_competence: bool = True
    train: TrainConfig = field(default_factory=learning_recipe)
    """The runs' training settings (navi_learner.config.learning_recipe by default). Each run gets its own
    seed, device, temporal core and the time budget; 0 actors or rollout length: learning_size's."""
    parallel: int = 1
    """Runs at once (processes sharing the device); their wall times then overlap."""
    gpus: int = 0
    """> 0: spread the runs round-robin over cuda:0 .. cuda:gpus-1, one process per run and at most
    `parallel` at once (so gpus = parallel = number of runs gives every run a GPU of its own)."""
    nproc: int = 1
    """> 1: every run trains data-parallel on this many ranks (one GPU each on CUDA), `actors` per rank;
    the runs go one after another."""
    protocol: EvalProtocol = field(default_factory=EvalProtocol)
    reward: tuple[tuple[str, float], ...] = ()
    """RewardConfig fields replaced in every env of the job (training, evaluation, baselines)."""
    procedural_share: float = 0.0
    """Share of the train corpus's scenes that are procedural (0: as built, 16 of 56); see prepare_splits."""
    obstacles: int = 0
    """Scripted moving obstacles per actor in every env of the job (EnvConfig.obstacles)."""
    squad: int = 0
    """Squads of this many actors that see and collide with each other, in every env (0: off)."""
    warmup_updates: int = 3
    """Untimed PPO updates of each arm in every process that trains runs, before its first run (warm_up);
    with nproc > 1 the ranks of every run take them before it: no run's clock then holds the compile (0:
    none; the first run of each arm compiles on its clock)."""


def prepare_splits(
    root: Path,
    resolution: int,
    device: str,
    pk3: Path | None,
    procedural_train: int = 16,
    procedural_unseen: int = 8,
    say: Say = print,
    procedural_share: float = 0.0,
) -> Splits:
    """Build (or reuse) the corpus parts under `root` and merge them into the train and unseen corpora.
    With `procedural_share` in (0, 1) and both parts present, the procedural train scenes are repeated in
    the train corpus until about that share of its scenes (so of the actors' time) is procedural."""
    if not 0.0 <= procedural_share < 1.0:
        raise ValueError(f"procedural_share must be in [0, 1), got {procedural_share}")
    from navi_env.corpus.folder import (
        build_corpus,
        build_default_corpus,
        corpus_is_current,
        merge_corpora,
        read_manifest,
    )

    have_pk3 = pk3 is not None and pk3.is_file()

    def part(name: str, build: Callable[[Path], object], real: bool = False) -> Path:
        """The corpus folder `name`, built unless it is there (a real-map one is rebuilt where its cubes
        were fitted under older compiler rules and the pk3 is at hand)."""
        folder = root / f"{name}-{resolution}"
        stale = real and have_pk3 and (folder / "manifest.json").is_file() and not corpus_is_current(folder)
        if stale or not (folder / "manifest.json").is_file():
            say(f"[bench learn] {'rebuilding' if stale else 'building'} {folder}")
            build(folder)
        return folder

    def progress(line: str) -> None:
        say(f"[bench learn]   {line}")

    train_parts = {
        "procedural": part(
            "procedural-train",
            lambda f: build_default_corpus(f, resolution, procedural_train, 0, device, progress),
        )
    }
    unseen_parts = {
        "procedural": part(
            "procedural-unseen",
            lambda f: build_default_corpus(f, resolution, procedural_unseen, 1000, device, progress),
        )
    }
    notes = []
    built = all(
        (root / f"openarena-{k}-{resolution}" / "manifest.json").is_file() for k in ("train", "unseen")
    )
    if built or have_pk3:
        maps = openarena_maps(pk3) if pk3 is not None and have_pk3 else []
        train_maps, held = split_openarena(maps)
        train_parts["openarena"] = part(
            "openarena-train",
            lambda f: build_corpus(
                [f"{pk3}:{m}" for m in train_maps], f, resolution, device, progress=progress
            ),
            real=True,
        )
        unseen_parts["openarena"] = part(
            "openarena-unseen",
            lambda f: build_corpus([f"{pk3}:{m}" for m in held], f, resolution, device, progress=progress),
            real=True,
        )
    else:
        notes.append(f"OpenArena maps not found at {pk3}: the splits hold procedural scenes only")
    train = root / f"train-{resolution}"
    unseen = root / f"unseen-{resolution}"
    repeats = 1
    if procedural_share > 0.0 and "openarena" in train_parts:
        n_p = len(read_manifest(train_parts["procedural"]).scenes)
        n_o = len(read_manifest(train_parts["openarena"]).scenes)
        repeats = max(1, round(procedural_share * n_o / ((1.0 - procedural_share) * n_p)))
        share = repeats * n_p / (repeats * n_p + n_o)
        notes.append(f"train corpus: the {n_p} procedural scenes {repeats} times, {share:.0%} of its scenes")
    merge_corpora(
        [train_parts["procedural"]] * repeats + [v for k, v in train_parts.items() if k != "procedural"],
        train,
    )
    merge_corpora(list(unseen_parts.values()), unseen)
    scenes = {f"train/{k}": [s.name for s in read_manifest(v).scenes] for k, v in train_parts.items()}
    scenes |= {f"unseen/{k}": [s.name for s in read_manifest(v).scenes] for k, v in unseen_parts.items()}
    return Splits(train, unseen, unseen_parts, scenes, notes)


class ArmSpec(NamedTuple):
    """An arm as parse_arm reads it."""

    core: TemporalCoreName
    engine: dict[str, Any]
    """EngineConfig fields its fresh engine replaces."""
    reward: dict[str, float]
    """RewardConfig weights its training env replaces, on top of the job's."""
    ppo: dict[str, Any]
    """PPOConfig settings (ARM_PPO_FIELDS) its training replaces, on top of the job's."""
    size: dict[str, int]
    """TrainConfig sizes (ARM_SIZE_FIELDS' values: n_actors, rollout_length) its training replaces."""


ARM_PPO_FIELDS = ("lr", "mean_bound_coef", "ent_coef", "clip_coef", "vf_coef", "gae_lambda", "gamma")
"""The PPOConfig settings an arm may name (numbers of the optimizer, the objective and the returns; the
job's options set the rest)."""


ARM_SIZE_FIELDS = {"actors": "n_actors", "rollout_length": "rollout_length"}
"""The run sizes an arm may name (its key -> the TrainConfig field): actors per run (per rank with --nproc)
and steps per rollout, in place of the job's --actors and --rollout-length."""


def size_number(key: str, value: str) -> int:
    """An arm's run size as a positive whole number: ValueError names the size where `value` is not one."""
    try:
        number = int(value)
    except ValueError:
        number = 0
    if number < 1:
        raise ValueError(f"{key} expects a positive whole number, got {value.strip()!r}")
    return number


def ppo_number(key: str, value: str) -> float:
    """An arm's PPO setting as a number: ValueError names the setting where `value` is not one, or is not a
    positive learning rate."""
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"{key} expects a number, got {value.strip()!r}") from None
    if key == "lr" and not number > 0.0:
        raise ValueError(f"lr expects a positive learning rate, got {value.strip()!r}")
    return number


def parse_arm(spec: str) -> ArmSpec:
    """An arm `CORE[/KEY=VALUE[,KEY=VALUE...]]`: a KEY that names a RewardConfig weight goes to its
    training env's reward, one of ARM_PPO_FIELDS to its PPO settings, one of ARM_SIZE_FIELDS to its run
    size, any other must be an EngineConfig field; ValueError names an unknown core or field, or a value
    that is not a number (a positive whole one for a size)."""
    from navi_env.config import RewardConfig

    core, _, rest = (part.strip() for part in spec.partition("/"))
    if core not in TEMPORAL_CORES:
        raise ValueError(
            f"arm {spec!r}: unknown temporal core {core!r}; choose from {', '.join(TEMPORAL_CORES)}"
        )
    items = [item for item in rest.split(",") if item.strip()]
    if "/" in spec and not items:
        raise ValueError(f"arm {spec!r}: name KEY=VALUE after /")
    weights = {f.name for f in fields(RewardConfig)}
    shapes = {f.name for f in fields(EngineConfig)} - {"temporal_core"}  # the core comes before the /
    for key in (item.partition("=")[0].strip() for item in items):
        if key not in weights | shapes | set(ARM_PPO_FIELDS) | set(ARM_SIZE_FIELDS):
            raise ValueError(
                f"arm {spec!r}: unknown field {key!r}: name an EngineConfig field (e.g. patch_size), a "
                "RewardConfig weight (e.g. collision_weight), a PPO setting "
                f"({', '.join(ARM_PPO_FIELDS)}) or a run size ({', '.join(ARM_SIZE_FIELDS)})"
            )
    to_reward = [item for item in items if item.partition("=")[0].strip() in weights]
    to_ppo = [item for item in items if item.partition("=")[0].strip() in ARM_PPO_FIELDS]
    to_size = [item for item in items if item.partition("=")[0].strip() in ARM_SIZE_FIELDS]
    rest_items = [
        item for item in items if item not in to_reward and item not in to_ppo and item not in to_size
    ]
    try:
        engine = engine_overrides(rest_items)
        reward = parse_reward_overrides(to_reward)
        ppo: dict[str, Any] = {
            key.strip(): ppo_number(key.strip(), value)
            for key, _, value in (i.partition("=") for i in to_ppo)
        }
        size = {
            ARM_SIZE_FIELDS[key.strip()]: size_number(key.strip(), value)
            for key, _, value in (i.partition("=") for i in to_size)
        }
    except ValueError as err:
        raise ValueError(f"arm {spec!r}: {err}") from err
    name: TemporalCoreName = "gru" if core == "gru" else "mambapy" if core == "mambapy" else "mamba2"
    return ArmSpec(name, engine, reward, ppo, size)


def arm_reward(cfg: LearnConfig, arm: str) -> dict[str, float]:
    """The RewardConfig weights an arm's training env replaces: the job's (--reward), then the arm's own."""
    return dict(cfg.reward) | parse_arm(arm).reward


def arm_slug(spec: str) -> str:
    """An arm's spec as a folder name: its separators as dashes."""
    return spec.replace("/", "-").replace(",", "-")


def arm_folder(spec: str, seed: int) -> str:
    """The run folder's name of (arm, seed)."""
    return f"{arm_slug(spec)}-seed{seed}"


def run_order(cfg: LearnConfig) -> list[tuple[str, int]]:
    """The job's (arm, seed) runs in the order they start: seed by seed, every arm of a seed before the
    next seed, so that arms compared in one job share its conditions (and, with --gpus, its GPUs)."""
    return [(arm, seed) for seed in cfg.seeds for arm in cfg.temporal_cores]


def train_config(cfg: LearnConfig, arm: str, seed: int, device: torch.device) -> TrainConfig:
    """The TrainConfig of one run of the benchmark: the job's settings (its engine with the arm's core
    and engine fields, its PPO settings and run sizes with the arm's), sized by learning_size where
    neither sets a size, with the run's seed, device and time budget and no periodic checkpoints."""
    core, overrides, _, ppo, size = parse_arm(arm)
    engine = replace(cfg.train.engine, temporal_core=core, **overrides)
    job = cfg.train
    arm_sized = replace(
        job,
        n_actors=size.get("n_actors", job.n_actors),
        rollout_length=size.get("rollout_length", job.rollout_length),
    )
    sized = learning_size(arm_sized, device)
    return replace(
        sized,
        ppo=replace(sized.ppo, **ppo),
        time_limit_s=cfg.time_budget_s,
        checkpoint_every=10**12,
        seed=seed,
        device=str(device),
        engine=engine,
    )


def train_env(splits: Splits, cfg: LearnConfig, arm: str, tcfg: TrainConfig, device: str, d: Dist) -> Any:
    """This process's training env of a run of `arm` (`tcfg`, train_config's): the train split's scenes as
    tcfg.rank_scenes deals them to rank d.rank, the run's seed offset by the rank, the reward weights of
    the job and of the arm (arm_reward), and the job's obstacles, squads and task."""
    return make_env(
        splits.train, tcfg.n_actors, device, tcfg.seed + d.rank, reward=arm_reward(cfg, arm),
        obstacles=cfg.obstacles, squad=cfg.squad, task=cfg.train.task, rank=d.rank, world=d.world,
        rank_scenes=tcfg.rank_scenes,
    )  # fmt: skip


def warm_up(
    cfg: LearnConfig,
    arm: str,
    splits: Splits,
    device: str,
    run_dir: Path,
    say: Say,
    dist: Dist | None = None,
) -> dict[str, Any]:
    """`cfg.warmup_updates` untimed updates of `arm` on the train split, outside every run's clock: they
    compile its rollout step and update in this process and put them into the compile cache on disk, so
    the runs after it do not compile on their clocks (a cold compile took 58-60 s of a first run's 200 s
    on an H200). As a rank of a data-parallel run (`dist`) every rank takes those updates together, with
    the collectives the run's graphs are built around; rank 0 alone says how long they took."""
    from navi_learner.ppo.train import train

    d = dist or Dist()
    started = time.perf_counter()
    tcfg = train_config(cfg, arm, cfg.seeds[0], torch.device(device))
    tcfg = replace(
        tcfg,
        total_steps=cfg.warmup_updates * tcfg.n_actors * tcfg.rollout_length * d.world,  # every rank's
        time_limit_s=0.0,
    )
    train(
        train_env(splits, cfg, arm, tcfg, device, d),
        tcfg,
        run_dir=run_dir,
        corpus_summary=corpus_summary(splits.train, "sdfdag"),
        progress=False,
        dist=d,
    )
    if device.startswith("cuda"):
        torch.cuda.empty_cache()
    seconds = time.perf_counter() - started
    where = f"{device} x {d.world} ranks" if d.active else device
    if d.main:
        say(
            f"[bench learn] warm-up of {arm} on {where}: {cfg.warmup_updates} untimed updates in {seconds:.0f} s"
        )
    return {"arm": arm, "device": where, "updates": cfg.warmup_updates, "seconds": seconds}


def run_one(
    splits: Splits,
    cfg: LearnConfig,
    arm: str,
    seed: int,
    device: str,
    run_dir: Path,
    baselines: dict[str, EvalMetrics],
    say: Say = say_stderr,
    dist: Dist | None = None,
) -> dict[str, Any]:
    """Train one (arm, seed) from scratch with the competence monitor; returns its result dict. As a
    rank of a data-parallel run (`dist`), this rank trains its actors on the train scenes as
    cfg.train.rank_scenes says (every one by default); rank 0 alone evaluates and returns the result (the other ranks return {})."""
    from navi_learner.evaluation.evaluate import CheckpointPolicy, evaluate
    from navi_learner.ppo.train import train

    d = dist or Dist()
    dev = torch.device(device)
    tcfg = train_config(cfg, arm, seed, dev)
    env = train_env(splits, cfg, arm, tcfg, device, d)
    monitor = None
    if d.main:
        monitor = CompetenceMonitor(
            eval_env(splits.unseen, cfg, device),
            cfg.protocol,
            cfg.eval_every_s,
            cfg.stop_at_competence,
            say=lambda line: say(f"[{arm} seed {seed}] {line}"),
            baselines=baselines,
        )
    started = time.perf_counter()
    result = train(
        env,
        tcfg,
        run_dir=run_dir,
        corpus_summary=corpus_summary(splits.train, "sdfdag"),
        progress=False,
        monitor=monitor,
        dist=d,
    )
    if monitor is None:
        return {}
    trained = CheckpointPolicy(result.final_checkpoint, dev, seed=cfg.protocol.seed)
    if (
        not monitor.curve or monitor.curve[-1]["step"] != result.step_id
    ):  # the budget ended between evaluations
        monitor.record(trained.policy, result.step_id, float(result.last_metrics.get("train_s", 0.0)))
    final = {}
    for name, path in splits.unseen_parts.items():
        part = eval_env(path, cfg, device)
        final[name] = asdict(evaluate(part, trained, cfg.protocol.steps, cfg.protocol.seed))
        final[name]["policy"] = f"trained ({arm}, seed {seed})"
    return {
        "arm": arm,
        "temporal_core": tcfg.engine.temporal_core,
        "seed": seed,
        "run_id": result.run_id,
        "checkpoint": str(result.final_checkpoint),
        "steps": result.step_id,
        "train_s": float(result.last_metrics.get("train_s", 0.0)),
        "wall_s": time.perf_counter() - started,
        "sps": result.sps,
        "competence": monitor.competence,
        "curve": monitor.curve,
        "final_by_split": final,
        "train_config": result.config.to_dict(),  # resolved: the rate and sizes it trained at
        "reward_overrides": arm_reward(cfg, arm),
        "mean_outside": float(result.last_metrics.get("mean_outside", math.nan)),
        "ranks": d.world,
    }


def eval_env(corpus: Path, cfg: LearnConfig, device: str) -> Any:
    """An evaluation env of the job's protocol over `corpus` (its actors, seed, episode length, reward
    overrides, obstacles and squads)."""
    p = cfg.protocol
    return make_env(
        corpus,
        p.actors,
        device,
        p.seed,
        episode_steps=p.episode_steps,
        reward=dict(cfg.reward),
        obstacles=cfg.obstacles,
        squad=cfg.squad,
        task=cfg.train.task,
    )


def baselines_by_split(splits: Splits, cfg: LearnConfig, device: str) -> dict[str, dict[str, EvalMetrics]]:
    """The task's baselines (competence.evaluate_baselines) on the whole unseen split ("all") and on each
    of its parts."""
    out = {"all": evaluate_baselines(eval_env(splits.unseen, cfg, device), cfg.protocol)}
    for name, path in splits.unseen_parts.items():
        out[name] = evaluate_baselines(eval_env(path, cfg, device), cfg.protocol)
    return out


def run_devices(device: str, gpus: int, runs: int) -> list[str]:
    """The device of each run: `device` for all, or cuda:0 .. cuda:gpus-1 round-robin when gpus > 0."""
    if gpus <= 0:
        return [device] * runs
    if not device.startswith("cuda"):
        raise ValueError("--gpus needs a CUDA device")
    return [f"cuda:{i % gpus}" for i in range(runs)]


class RunJob(NamedTuple):
    """One (arm, seed) run of the job: what a process needs to train and evaluate it."""

    splits: Splits
    cfg: LearnConfig
    arm: str
    seed: int
    device: str
    run_dir: Path
    baselines: dict[str, EvalMetrics]


def _child(job: RunJob) -> dict[str, Any]:
    if job.device.startswith("cuda:"):
        torch.cuda.set_device(torch.device(job.device))  # extensions and graphs use the current device
    return run_one(*job)


def gpu_lanes(runs: int, gpus: int) -> list[list[int]]:
    """The job's runs (indices, placed round-robin by run_devices) per GPU, each GPU's in job order: one
    process per GPU trains its lane one run after another. (A plain pool hands the next run to whichever
    worker is free, which puts two runs on one GPU when runs of unequal length finish out of turn.)"""
    return [list(range(g, runs, gpus)) for g in range(gpus)]


def warmup_folder(out: Path, arm: str, device: str) -> Path:
    """The run folder of an arm's warm-up on `device`."""
    return out / "runs" / f"{arm_slug(arm)}-warmup-{device.replace(':', '')}"


def _lane(jobs: list[RunJob], say: Say = say_stderr) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One process's runs in turn, after the compile warm-up of each of their arms in this process (its
    compiled code then serves the runs): (warm-ups, runs)."""
    warmups = []
    if jobs and jobs[0].cfg.warmup_updates > 0:
        job = jobs[0]
        if job.device.startswith("cuda:"):
            torch.cuda.set_device(torch.device(job.device))
        for arm in dict.fromkeys(j.arm for j in jobs):
            folder = warmup_folder(job.run_dir.parent.parent, arm, job.device)
            warmups.append(warm_up(job.cfg, arm, job.splits, job.device, folder, say))
    return warmups, [_child(job) for job in jobs]


RANK_ENTRY = ["-m", "navi_bench.learn_rank"]
"""How torchrun starts a rank of a data-parallel run (learn_rank.py calls rank_main)."""


class RankRunError(RuntimeError):
    """A data-parallel run of the job ended without a result (its ranks' error is on stderr)."""


def rank_files(run_dir: Path) -> tuple[Path, Path]:
    """(job, result) files of a data-parallel run, beside its run folder."""
    return run_dir.parent / f"{run_dir.name}.job", run_dir.parent / f"{run_dir.name}.result.json"


def run_ranks(run: RunJob, nproc: int) -> dict[str, Any]:
    """One run of the job on nproc data-parallel ranks through torchrun: the job goes to a file beside
    the run folder, rank 0 writes the run's result next to it."""
    job, answer = rank_files(run.run_dir)
    job.parent.mkdir(parents=True, exist_ok=True)
    answer.unlink(missing_ok=True)
    job.write_bytes(pickle.dumps(run))
    # the others wait in a collective while rank 0 evaluates (its first evaluation compiles): 300 s
    env = {ddp.TIMEOUT_ENV: "300", **os.environ}
    code = ddp.relaunch(nproc, [str(job)], env=env, entry=RANK_ENTRY)
    if code != 0 or not answer.is_file():
        raise RankRunError(
            f"the {nproc}-rank run of {run.arm} seed {run.seed} failed with exit code {code} (its error is above)"
        )
    result = dict(json.loads(answer.read_text()))
    job.unlink()
    answer.unlink()  # the run's result lives on in result.json
    return result


def rank_main(job: Path) -> None:
    """A rank of run_ranks' run (started by torchrun): join the process group, train this rank's share,
    and on rank 0 write the run's result beside the job file."""
    run: RunJob = pickle.loads(job.read_bytes())
    d, dev = ddp.setup(run.device)
    code = 0
    try:
        warm = None
        if run.cfg.warmup_updates > 0:  # in these processes, so the run's graphs are compiled off its clock
            folder = run.run_dir.parent / f"{run.run_dir.name}-warmup"
            warm = warm_up(run.cfg, run.arm, run.splits, dev, folder, say_stderr, dist=d)
        result = run_one(*run._replace(device=dev), dist=d)
        if d.main:
            if warm is not None:
                result["warmup"] = {**warm, "seed": run.seed}
            rank_files(run.run_dir)[1].write_text(json.dumps(jsonable(result)))
    except ddp.DistError as err:
        print(f"error: {err}", file=sys.stderr)
        code = 1
    finally:
        ddp.shutdown(d)
    ddp.leave(d, code)


def censored_median(values: list[float | None]) -> float | None:
    """The median of `values` where None is a run that never got there (beyond its budget, so larger
    than every number): None when the median falls on such a run. Over seeds 0-2 with one competent at
    62 s it is None, not 62: a median of the competent seeds alone would flatter an arm that mostly fails."""
    if not values:
        return None
    mid = statistics.median(math.inf if v is None else v for v in values)
    return None if math.isinf(mid) else mid


LATE_METRICS = ("collisions_per_1k", "coverage_per_1k", "success_rate", "spl")
"""The curve's metrics that late_means averages (those a point carries: point-goal runs add the last two)."""


def late_means(curve: list[dict[str, Any]], budget_s: float) -> dict[str, Any]:
    """The mean of each of a run's unseen metrics over its evaluations in the second half of the training
    budget (train_s >= budget_s / 2), and their count ("evaluations"; the metrics None where there are
    none). Near the explore bar one evaluation of 256 actors decides whether a seed is competent (its
    collisions interval spans about ±0.1 per 1,000 steps against a bar of 0.035), so arms are compared
    on these means as well as on the first evaluation that met the bar. A run stopped at competence
    holds fewer of them (`--full-budget` keeps every run to its budget)."""
    late = [p for p in curve if p["train_s"] >= budget_s / 2]
    out: dict[str, Any] = {"evaluations": len(late)}
    for key in LATE_METRICS:
        values = [p[key] for p in late if p.get(key) is not None]
        out[key] = statistics.fmean(values) if values else None
    return out


def median_of(values: list[float | None]) -> float | None:
    """The median of the values that are not None; None where none are."""
    present = [v for v in values if v is not None]
    return statistics.median(present) if present else None


def summarise(runs: list[dict[str, Any]], budget_s: float) -> dict[str, Any]:
    """Per arm (in the order of `runs`): competent seeds, median training seconds and env steps to
    competence over all its seeds (a seed that did not get there counts as beyond the budget, so the
    median is null unless more than half got there; censored_median), the median final unseen
    metrics, and the median over seeds of each run's late means (late_means: collisions and coverage,
    and point-goal's success and SPL)."""
    out: dict[str, Any] = {}
    for arm in dict.fromkeys(r["arm"] for r in runs):
        mine = [r for r in runs if r["arm"] == arm]
        reached = [r["competence"] for r in mine]  # None where the seed never got there
        hits = sum(c is not None for c in reached)
        last = [r["curve"][-1] for r in mine if r["curve"]]
        late = [late_means(r["curve"], budget_s) for r in mine]
        out[arm] = {
            "seeds": len(mine),
            "competent_seeds": hits,
            "median_train_s_to_competence": censored_median([c and c["train_s"] for c in reached]),
            "median_steps_to_competence": censored_median([c and c["step"] for c in reached]),
            "competent_within_budget": hits == len(mine),
            "budget_s": budget_s,
            "median_final_collisions_per_1k": median_of([p["collisions_per_1k"] for p in last]),
            "median_final_coverage_per_1k": median_of([p["coverage_per_1k"] for p in last]),
            "median_sps": statistics.median(r["sps"] for r in mine),
            "median_late_collisions_per_1k": median_of([m["collisions_per_1k"] for m in late]),
            "median_late_coverage_per_1k": median_of([m["coverage_per_1k"] for m in late]),
        }
        if last and last[0].get("success_rate") is not None:  # point-goal runs
            out[arm]["median_final_success_rate"] = median_of([p["success_rate"] for p in last])
            out[arm]["median_final_spl"] = median_of([p["spl"] for p in last])
            out[arm]["median_late_success_rate"] = median_of([m["success_rate"] for m in late])
            out[arm]["median_late_spl"] = median_of([m["spl"] for m in late])
    return out


def warmup_label(warm: dict[str, Any]) -> str:
    """A warm-up as the report names it: its arm, and the seed of the data-parallel run it preceded."""
    return f"{warm['arm']} seed {warm['seed']}" if "seed" in warm else str(warm["arm"])


def figure(value: float | None) -> str:
    """A metric as the report prints it: 4 significant digits, "-" where there is none."""
    return "-" if value is None else f"{value:.4g}"


def report_markdown(result: dict[str, Any], baselines: dict[str, dict[str, EvalMetrics]]) -> str:
    """report.md: the summary per arm, each run, and the per-split tables of every run."""
    lines = ["# navi bench learn", "", f"device {result['device']}, {result['date']}", ""]
    goal = result["config"]["train"].get("task") == "pointgoal"
    budget = float(next(iter(result["summary"].values()))["budget_s"]) if result["summary"] else 0.0
    finals = ("success", "SPL") if goal else ("coll/1k", "cov/1k")
    metrics = ("success_rate", "spl") if goal else ("collisions_per_1k", "coverage_per_1k")
    lines += [
        "| arm | seeds | competent | median s to competence (all seeds) | median steps | "
        f"final {finals[0]} | final {finals[1]} | late {finals[0]} | late {finals[1]} | SPS |"
    ]
    lines += ["| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for arm, s in result["summary"].items():
        t, n = s["median_train_s_to_competence"], s["median_steps_to_competence"]
        beyond = f"> {s['budget_s']:.0f} (not reached)"
        shown = [figure(s.get(f"median_{when}_{m}")) for when in ("final", "late") for m in metrics]
        lines.append(
            f"| {arm} | {s['seeds']} | {s['competent_seeds']} | {beyond if t is None else f'{t:.0f}'} | "
            f"{'-' if n is None else f'{n:,.0f}'} | {' | '.join(shown)} | {s['median_sps']:.0f} |"
        )
    lines += [
        "",
        f"Final: the last evaluation of each seed; late: the mean of each seed's evaluations in the second half "
        f"of the budget (from {budget / 2:.0f} s of training); both the median over the seeds.",
    ]
    warm = result.get("warmups", [])
    if warm:
        seconds = ", ".join(f"{warmup_label(w)} {w['seconds']:.0f} s" for w in warm)
        each = "data-parallel run" if "seed" in warm[0] else "arm"
        lines += [
            "",
            f"Compile warm-up before the runs, outside their clocks: {warm[0]['updates']} untimed updates per {each} ({seconds}).",
        ]
    lines += [
        "",
        f"| arm | seed | competence (train s, steps) | steps | train s | late {finals[0]} | late {finals[1]} "
        "| late evaluations |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in result["runs"]:
        c = r["competence"]
        hit = f"{c['train_s']:.0f} s, {c['step']:,}" if c else "not reached"
        late = late_means(r["curve"], budget)
        lines.append(
            f"| {r['arm']} | {r['seed']} | {hit} | {r['steps']:,} | {r['train_s']:.0f} | "
            f"{figure(late[metrics[0]])} | {figure(late[metrics[1]])} | {late['evaluations']} |"
        )
    for r in result["runs"]:
        for part, metrics in r["final_by_split"].items():
            rows = [EvalMetrics(**metrics), *baselines[part].values()]
            lines += [
                "",
                f"## {r['arm']} seed {r['seed']}, unseen {part}",
                "",
                comparison_table(rows),
            ]
            contacts = contact_line(rows[0])
            if contacts:
                lines += ["", contacts]
    return "\n".join(lines) + "\n"


def bench_learn(
    cfg: LearnConfig,
    out: Path,
    device: str,
    resolution: int,
    corpus_root: Path,
    pk3: Path | None,
    say: Say = print,
) -> dict[str, Any]:
    """The whole benchmark; writes and returns result.json's content."""
    for arm in cfg.temporal_cores:
        weights = arm_reward(cfg, arm)  # parse_arm's errors name the arm
        try:
            reward_config(weights, cfg.train.task)  # and so does a weight the task does not read, up front
        except ValueError as err:
            raise ValueError(f"arm {arm!r}: {err}") from err
    if len(set(cfg.temporal_cores)) != len(cfg.temporal_cores):
        raise ValueError(f"an arm is named twice: {', '.join(cfg.temporal_cores)}")
    if cfg.nproc < 1:
        raise ValueError(f"nproc must be at least 1, got {cfg.nproc}")
    if cfg.nproc > 1 and (cfg.parallel > 1 or cfg.gpus > 0):
        raise ValueError(
            "--nproc trains each run on several ranks, one run at a time: leave out --parallel and --gpus"
        )
    if cfg.nproc > 1 and device.startswith("cuda") and torch.cuda.device_count() < cfg.nproc:
        raise ValueError(
            f"--nproc {cfg.nproc} needs {cfg.nproc} GPUs; this machine has {torch.cuda.device_count()}"
        )
    out.mkdir(parents=True, exist_ok=True)
    splits = prepare_splits(
        corpus_root, resolution, device, pk3, say=say, procedural_share=cfg.procedural_share
    )
    say(f"[bench learn] train {splits.train}, unseen {splits.unseen}")
    baselines = baselines_by_split(splits, cfg, device)
    for part, b in baselines.items():
        say(f"[bench learn] baselines on unseen {part}:\n" + comparison_table(list(b.values())))
    runs_wanted = run_order(cfg)
    places = run_devices(device, cfg.gpus, len(runs_wanted))
    jobs = [
        RunJob(splits, cfg, arm, seed, place, out / "runs" / arm_folder(arm, seed), baselines["all"])
        for (arm, seed), place in zip(runs_wanted, places, strict=True)
    ]
    warmups: list[dict[str, Any]] = []
    started = time.perf_counter()
    if cfg.nproc > 1:  # every run's ranks warm up first, in their own processes (rank_main)
        runs = [run_ranks(job, cfg.nproc) for job in jobs]
        warmups = [run.pop("warmup") for run in runs if "warmup" in run]
    elif cfg.gpus > 0 and cfg.parallel == cfg.gpus:  # one process per GPU, its runs one after another
        lanes = gpu_lanes(len(jobs), cfg.gpus)
        with multiprocessing.get_context("spawn").Pool(cfg.gpus) as pool:
            done = pool.map(_lane, [[jobs[k] for k in lane] for lane in lanes])
        warmups = [w for lane_warmups, _ in done for w in lane_warmups]
        by_job = {
            k: run
            for lane, (_, results) in zip(lanes, done, strict=True)
            for k, run in zip(lane, results, strict=True)
        }
        runs = [by_job[k] for k in range(len(jobs))]
    elif cfg.parallel > 1:  # the warm-up here fills the compile cache on disk that the pool's workers read
        warmups = [
            warm_up(cfg, arm, splits, device, warmup_folder(out, arm, device), say)
            for arm in cfg.temporal_cores
        ]
        with multiprocessing.get_context("spawn").Pool(cfg.parallel) as pool:
            runs = pool.map(_child, jobs)
    else:
        warmups, runs = _lane(jobs, say)
    notes = list(splits.notes)
    result: dict[str, Any] = {
        "device": (torch.cuda.get_device_name() if device.startswith("cuda") else "cpu")
        + (f" x {cfg.gpus} (one run per GPU at a time)" if cfg.gpus > 0 else "")
        + (f" x {cfg.nproc} (each run data-parallel on {cfg.nproc} ranks)" if cfg.nproc > 1 else ""),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "config": asdict(replace(cfg, seeds=list(cfg.seeds), temporal_cores=list(cfg.temporal_cores))),  # type: ignore[arg-type]
        "reward": asdict(reward_config(dict(cfg.reward), cfg.train.task)),
        "resolution": resolution,
        "splits": {
            "scenes": splits.scenes,
            "train": str(splits.train),
            "unseen": str(splits.unseen),
            "notes": notes,
        },
        "competence_bar": (
            "success >= 0.9, SPL >= 0.75 and fewer collisions per episode than greedy, unseen split, same seed"
            if cfg.train.task == "pointgoal"
            else "collisions/1k <= 0.5 x reactive and coverage/1k >= 1.5 x reactive, unseen split, same seed"
        ),
        "baselines": {part: {k: asdict(v) for k, v in b.items()} for part, b in baselines.items()},
        "warmups": warmups,
        "runs": runs,
        "summary": summarise(runs, cfg.time_budget_s),
        "wall_s": time.perf_counter() - started,
    }
    curves = {f"{r['arm']} seed {r['seed']}": r["curve"] for r in runs}
    why_not = plot_curves(curves, baselines["all"], out / "learning_curves.png")
    if why_not:
        notes.append(why_not)
    (out / "curves.json").write_text(json.dumps(jsonable(curves), indent=1))
    (out / "result.json").write_text(json.dumps(jsonable(result), indent=1))
    (out / "report.md").write_text(report_markdown(result, baselines))
    return result
