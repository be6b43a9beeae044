"""`navi bench transfer`: does a drone trained on procedural scenes alone fly real maps it never saw?

Protocol (docs/TRAINING.md, "Real maps never seen"):
- Arms. Each arm trains the learning recipe (navi_learner.config.learning_recipe, learning_size's actors
  and rollouts) from scratch for `budget_s` seconds of training on its own train split, once per seed:
  - `procedural[:SEMANTICS[:FAMILY+FAMILY...]]`: procedural scenes of seed 0 (the main job's corpus),
    face classes by SEMANTICS (object or surface, navi_compiler.ingest.procedural.Semantics; default
    object), of the listed families (default: the default families; FAMILY@S scales that entry's scenes by
    up to S);
  - `openarena`: the OpenArena maps outside the held-out fifth (every fifth map by name, as `navi bench
    learn` holds out): the upper reference, a drone that has seen real maps;
  - either followed by `/KEY=VALUE[,KEY=VALUE...]`: the arm trains with those RewardConfig fields
    replaced (`procedural/structure_weight=0`) or a fresh engine with those EngineConfig fields
    (`procedural/action_input=1`), or starting from a checkpoint's weights (`procedural/init_from=explore`:
    the shipped explore reference, in the engine it stored with the arm's fields on top), on the same
    corpus as the arm without them, so that a reward, engine or initialisation lever is measured beside
    the recipe in one job; evaluation never reads the reward.
- Evaluation. Every arm's final checkpoint flies (EvalProtocol, same env seed; as its task is flown
  everywhere, ACTION_NOISE, or once per `action_noise` scale S: its mean action at 0, its actions sampled
  with S times its learned std above, each scale but the task's a row of its own, `ARM, mean action` or
  `ARM, sampled xS`) on:
  - `openarena`: all OpenArena maps, per map too (no procedural arm has seen any of them);
  - `openarena-held-out`: the held-out fifth, which no arm has seen: the parity comparison;
  - `procedural`: procedural scenes of seed 1000, every family, in the arm's semantics.
  The task's baselines fly the same envs (random and the reactive avoider; random, greedy and oracle
  for point-goal). On `openarena` every collision is classed and counted per map
  (navi_learner.evaluation.collisions: the surface touched, thin geometry behind it, pinned contacts, the
  pinned ones pushing into the nearest surface in view, and contacts the view's rays did not show).
- Open floor. Every explore run's final checkpoint also flies the open-floor probe
  (navi_learner.evaluation.open_floor, `navi bench openfloor`): does it hold its height over flat floors
  whose walls lie beyond its view clearance, or sink to the floor as large open maps show?
- Runs are placed one per GPU (`gpus`), each GPU working through its share in turn, after a few
  untimed updates that fill the compile cache (WarmupJob), so that every run's budget is training; the
  corpora are built once under `root` and reused.
Output folder: result.json and report.md (and transfer.png where matplotlib is installed).
"""

from __future__ import annotations

import json
import multiprocessing
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import torch

from navi_bench.learn import Say, say_stderr
from navi_env.config import EnvConfig
from navi_env.corpus.openarena import openarena_maps, split_openarena
from navi_learner.config import TrainConfig, learning_recipe, learning_size
from navi_learner.envs.factory import corpus_summary, make_env, reward_config
from navi_learner.evaluation.collisions import COUNTS, PINNED_STEPS, CollisionSites
from navi_learner.evaluation.competence import EvalProtocol, baseline_policies
from navi_learner.evaluation.evaluate import (
    COLLISION_FLOOR_PER_1K,
    action_noise,
    comparison_table,
    evaluate,
    jsonable,
    observers,
)
from navi_learner.evaluation.goal_flights import FLIGHTS, NEAR_M, GoalFlights
from navi_learner.evaluation.open_floor import (
    OpenFloorConfig,
    build_open_floors,
    open_floor_env,
    open_floor_probe,
    probe_table,
)

PROCEDURAL_TRAIN = 16
"""Procedural train scenes per arm (the main job's corpus size on CUDA)."""
TRAIN_SEED, UNSEEN_SEED = 0, 1000
"""Seeds of the procedural train and unseen scenes (the main job's)."""
WARMUP_UPDATES = 3
"""Untimed PPO updates each worker runs before its first timed run (WarmupJob)."""


@dataclass(frozen=True)
class Arm:
    """What one arm trains on (see the module docstring for the spec syntax)."""

    spec: str
    real: bool
    semantics: str = "object"
    families: tuple[str, ...] = ()
    reward: tuple[tuple[str, float], ...] = ()
    """RewardConfig fields the arm's training replaces (name, value)."""
    engine: tuple[tuple[str, Any], ...] = ()
    """EngineConfig fields of the arm's fresh engine (name, value), on top of the job's engine."""
    init_from: str = ""
    """The weights its runs start from (TrainConfig.init_from: a checkpoint, or a task's reference)."""

    @property
    def key(self) -> str:
        """A folder-safe name of its train corpus."""
        if self.real:
            return "openarena"
        return f"procedural-{self.semantics}-{'+'.join(self.families) or 'all'}"

    @property
    def run_key(self) -> str:
        """A folder-safe name of its runs: the corpus's, the reward and engine fields it replaces, and the
        checkpoint its runs start from."""
        fields_ = [f"{k}={_value(v)}" for k, v in (*self.reward, *self.engine)]
        if self.init_from:
            fields_.append(f"init_from={Path(self.init_from).stem}")
        return "-".join([self.key, *fields_])


def _value(v: Any) -> str:
    """A field's value in a folder name: 1 or 0 for a flag, a number as %g, a named choice as named."""
    return str(int(v)) if isinstance(v, bool) else v if isinstance(v, str) else f"{v:g}"


def parse_arm(spec: str) -> Arm:
    """An Arm from `openarena` or `procedural[:SEMANTICS[:FAMILY+FAMILY...]]` (an entry FAMILY@S scales its
    scenes by up to S, navi_compiler.ingest.procedural.parse_entry), either followed by
    `/KEY=VALUE[,KEY=VALUE...]` (RewardConfig fields, numbers; EngineConfig fields of a fresh engine,
    e.g. action_input=1; or init_from=CHECKPOINT, a task's name for its shipped reference: the weights
    the runs start from); ValueError on anything else."""
    from navi_learner.config import EngineConfig, engine_overrides
    from navi_learner.envs.factory import parse_reward_overrides
    from navi_learner.serving.references import checkpoint_path

    base, slash, overrides = spec.strip().partition("/")
    items = [o for o in overrides.split(",") if o.strip()]
    inits = [o.partition("=")[2].strip() for o in items if o.partition("=")[0].strip() == "init_from"]
    items = [o for o in items if o.partition("=")[0].strip() != "init_from"]
    if len(inits) > 1 or (inits and not checkpoint_path(inits[0]).is_file()):
        raise ValueError(f"arm {spec!r}: init_from names one checkpoint file or task reference, got {inits}")
    engine_fields = {f.name for f in fields(EngineConfig)}
    to_engine = [o for o in items if o.partition("=")[0].strip() in engine_fields]
    try:
        reward = tuple(parse_reward_overrides([o for o in items if o not in to_engine]).items())
        engine = tuple(engine_overrides(to_engine).items())
        EngineConfig(**dict(engine))  # the fields' own bounds
    except (TypeError, ValueError) as err:
        raise ValueError(f"arm {spec!r}: {err}") from err
    if slash and not (reward or engine or inits):
        raise ValueError(f"arm {spec!r}: name KEY=VALUE after /")
    arm = _parse_corpus_arm(base, spec)
    return replace(arm, spec=spec.strip(), reward=reward, engine=engine, init_from=inits[0] if inits else "")


def _parse_corpus_arm(base: str, spec: str) -> Arm:
    """The Arm of the part of a spec before any `/`."""
    from navi_compiler.ingest.procedural import SEMANTICS, parse_entry

    parts = base.split(":")
    if parts == ["openarena"]:
        return Arm(base, real=True)
    if parts[0] != "procedural" or len(parts) > 3:
        raise ValueError(f"arm {spec!r}: expected openarena or procedural[:SEMANTICS[:FAMILY+FAMILY...]]")
    semantics = parts[1] if len(parts) > 1 and parts[1] else "object"
    if semantics not in {s.value for s in SEMANTICS}:
        raise ValueError(f"arm {spec!r}: semantics must be one of {', '.join(s.value for s in SEMANTICS)}")
    families = tuple(f for f in parts[2].split("+") if f) if len(parts) > 2 else ()
    for entry in families:
        try:
            parse_entry(entry)
        except ValueError as err:
            raise ValueError(f"arm {spec!r}: {err}") from err
    return Arm(base, real=False, semantics=semantics, families=families)


@dataclass(frozen=True)
class TransferConfig:
    """One `navi bench transfer` job."""

    arms: tuple[Arm, ...]
    seeds: tuple[int, ...] = (0, 1, 2)
    budget_s: float = 240.0
    """Training seconds per run."""
    train: TrainConfig = field(default_factory=learning_recipe)
    """The runs' settings (the learning recipe); 0 actors or rollout length: learning_size's."""
    protocol: EvalProtocol = field(default_factory=lambda: EvalProtocol(actors=1000))
    """The evaluation: 1,000 actors spread over the scenes (20 per OpenArena map) x 1,000 steps."""
    gpus: int = 0
    """> 0: one run per GPU at a time on cuda:0 .. cuda:gpus-1 (and the corpora built on them in parallel)."""
    procedural_train: int = PROCEDURAL_TRAIN
    procedural_unseen: int = 0
    """Unseen procedural scenes (0: one per family)."""
    openarena_maps: int = 0
    """Use only the first this many OpenArena maps by name (0: all; small jobs and tests)."""
    open_floor: OpenFloorConfig | None = field(default_factory=OpenFloorConfig)
    """The open-floor probe each explore run's final checkpoint flies (None: none)."""
    action_noise: tuple[float, ...] = ()
    """Every final checkpoint flies once per scale: 0 its mean action, S > 0 its actions sampled with S
    times its learned std, drawn from the protocol's seed (empty: the task's ACTION_NOISE alone)."""

    def noises(self) -> tuple[float, ...]:
        """The scales every final checkpoint flies with."""
        return self.action_noise or (action_noise(self.train.task),)


def flown_as(spec: str, noise: float, task: str) -> str:
    """The row of an arm's checkpoints flown with `noise`: the arm's own name when its task flies so
    (ACTION_NOISE), else named after the mean action (0) or the spread."""
    if noise == action_noise(task):
        return spec
    return f"{spec}, mean action" if noise == 0 else f"{spec}, sampled x{noise:g}"


@dataclass(frozen=True)
class Corpora:
    """The corpus folders of one job."""

    train: dict[str, Path]
    """Arm key -> its train corpus."""
    unseen: dict[str, dict[str, Path]]
    """Arm key -> evaluation part -> corpus."""
    scenes: dict[str, list[str]]
    notes: list[str] = field(default_factory=list)


class BuildJob:
    """One corpus to build on one device (a picklable callable for the worker processes). `share` builds
    run side by side (one per GPU), so each compiles on its share of the CPU cores and memory."""

    def __init__(self, out: Path, kind: str, args: dict[str, Any], share: int = 1) -> None:
        self.out, self.kind, self.args, self.share = out, kind, args, share

    def __call__(self, device: str, say: Say) -> None:
        from navi_env.corpus.folder import (
            build_corpus,
            build_default_corpus,
            compile_workers,
            corpus_is_current,
        )

        if (self.out / "manifest.json").is_file() and (
            self.kind != "openarena" or corpus_is_current(self.out)
        ):
            return
        count = len(self.args["sources"]) if self.kind == "openarena" else self.args["count"]
        workers = compile_workers(self.args["resolution"], count, self.share)
        say(f"[bench transfer] building {self.out} on {device}, {workers} compiling at a time")
        started = time.perf_counter()
        if self.kind == "procedural":
            build_default_corpus(self.out, device=device, workers=workers, **self.args)
        else:
            build_corpus(self.args["sources"], self.out, self.args["resolution"], device, workers=workers)
        say(f"[bench transfer] built {self.out} in {time.perf_counter() - started:.0f} s")


def pointgoal_scenes(folder: Path, device: str) -> tuple[list[str], list[str]]:
    """The scenes of a corpus folder where point-goal episodes can be posed (some spawn has a goal within
    the env's goal distances, EnvConfig().goal), and a note for each scene where none can."""
    from navi_env.corpus.folder import load_corpus_folder
    from navi_env.sim.goals import scene_table

    corpus, manifest = load_corpus_folder(folder, device)
    spawns, env = manifest.spawn_tensors(), EnvConfig(task="pointgoal")
    keep: list[str] = []
    notes: list[str] = []
    for s, entry in enumerate(manifest.scenes):
        try:
            scene_table(corpus, s, spawns[s], env.goal, env.drone_radius)
        except ValueError as err:
            notes.append(f"point-goal episodes cannot be posed on {entry.name} ({err}): it is left out")
            continue
        keep.append(entry.name)
    return keep, notes


def plan_corpora(
    cfg: TransferConfig, root: Path, resolution: int, pk3: Path | None, device: str = "cpu"
) -> tuple[list[BuildJob], Callable[[], Corpora]]:
    """The build jobs of the job's corpora under `root` and a function that, once they are built, merges
    the OpenArena parts and returns the Corpora. For point-goal episodes the OpenArena parts keep only the
    maps where a goal can be posed (pointgoal_scenes on `device`); each map left out is noted."""
    from navi_compiler.ingest.procedural import FAMILIES
    from navi_env.corpus.folder import corpus_is_current, merge_corpora, read_manifest, subset_corpus

    jobs: list[BuildJob] = []
    notes: list[str] = []
    unseen_count = cfg.procedural_unseen or len(FAMILIES)
    train: dict[str, Path] = {}
    unseen: dict[str, dict[str, Path]] = {}
    have_maps = pk3 is not None and pk3.is_file()
    arms = [a for a in cfg.arms if have_maps or not a.real]
    if not have_maps:
        notes.append(f"OpenArena maps not found at {pk3}: the openarena arm and parts are left out")
    chunks: list[Path] = []
    maps: list[str] = []
    if have_maps:
        assert pk3 is not None
        maps = openarena_maps(pk3)[: cfg.openarena_maps or None]
        pieces = max(1, cfg.gpus)
        for k in range(pieces):
            mine = maps[k::pieces]
            if mine:
                chunks.append(root / f"openarena-{len(maps)}maps-{k}of{pieces}-{resolution}")
                sources = [f"{pk3}:{m}" for m in mine]
                jobs.append(
                    BuildJob(chunks[-1], "openarena", {"sources": sources, "resolution": resolution}, pieces)
                )
    for arm in arms:
        if arm.real:
            continue
        folder = root / f"{arm.key}-train-{resolution}"
        if folder not in [j.out for j in jobs]:
            args = {
                "resolution": resolution,
                "count": cfg.procedural_train,
                "seed": TRAIN_SEED,
                "families": list(arm.families) or None,
                "semantics": arm.semantics,
            }
            jobs.append(BuildJob(folder, "procedural", args, max(1, cfg.gpus)))
        train[arm.key] = folder
    for semantics in sorted({a.semantics for a in arms}):
        folder = root / f"procedural-{semantics}-unseen-{unseen_count}-{resolution}"
        args = {
            "resolution": resolution,
            "count": unseen_count,
            "seed": UNSEEN_SEED,
            "semantics": semantics,
            "families": [f.value for f in FAMILIES],
        }
        jobs.append(BuildJob(folder, "procedural", args, max(1, cfg.gpus)))

    def finish() -> Corpora:
        scenes: dict[str, list[str]] = {}
        real: dict[str, Path] = {}
        if chunks:
            train_maps, held = split_openarena(maps)
            names = {m: Path(m).stem for m in maps}
            merged = root / f"openarena-{len(maps)}maps-all-{resolution}"
            if not corpus_is_current(merged):
                merge_corpora(chunks, merged, by_name=True)
            by_name = {s.name: s for s in read_manifest(merged).scenes}
            tag = f"{len(maps)}maps"
            if cfg.train.task == "pointgoal":
                posable, left_out = pointgoal_scenes(merged, device)
                notes.extend(left_out)
                if len(posable) < len(by_name):
                    tag += f"-pointgoal{len(posable)}"
                    every = merged
                    merged = root / f"openarena-{tag}-all-{resolution}"
                    if not corpus_is_current(merged):
                        subset_corpus(every, posable, merged)
                by_name = {name: by_name[name] for name in posable}
            for part, chosen in (("train", train_maps), ("held-out", held)):
                folder = root / f"openarena-{tag}-{part}-{resolution}"
                keep = [names[m] for m in chosen if names[m] in by_name]
                if not corpus_is_current(folder):
                    subset_corpus(merged, keep, folder)
                real[part] = folder
            real["all"] = merged
            train["openarena"] = real["train"]
            scenes["openarena/train"] = [names[m] for m in train_maps if names[m] in by_name]
            scenes["openarena/held-out"] = [names[m] for m in held if names[m] in by_name]
        for arm in arms:
            parts = {"procedural": root / f"procedural-{arm.semantics}-unseen-{unseen_count}-{resolution}"}
            if real:
                parts = {"openarena": real["all"], "openarena-held-out": real["held-out"], **parts}
            unseen[arm.key] = parts
        for key, folder in train.items():
            scenes[f"train/{key}"] = [s.name for s in read_manifest(folder).scenes]
        return Corpora(train, unseen, scenes, notes)

    return jobs, finish


@dataclass(frozen=True)
class RunJob:
    """One (arm, seed) run: train, then evaluate on the arm's unseen parts (once per action noise)."""

    arm: Arm
    seed: int
    cfg: TransferConfig
    train: Path
    unseen: dict[str, Path]
    run_dir: Path
    floors: dict[float, Path] = field(default_factory=dict)
    """The open-floor probe's scenes by width (empty: no probe)."""

    def __call__(self, device: str, say: Say) -> list[dict[str, Any]]:
        """One row per action noise (TransferConfig.action_noise), each of the same trained checkpoint."""
        from navi_learner.ppo.learner import init_engine
        from navi_learner.ppo.train import train

        dev = torch.device(device)
        tcfg = replace(
            learning_size(self.cfg.train, dev),
            time_limit_s=self.cfg.budget_s,
            checkpoint_every=10**12,
            seed=self.seed,
            device=device,
        )
        if self.arm.init_from:  # the checkpoint's engine, the arm's fields on top
            engine = init_engine(self.arm.init_from, tcfg.engine.temporal_core, dict(self.arm.engine))
            tcfg = replace(tcfg, init_from=self.arm.init_from, engine=engine)
        elif self.arm.engine:
            tcfg = replace(tcfg, engine=replace(tcfg.engine, **dict(self.arm.engine)))
        say(f"[bench transfer] {self.arm.spec} seed {self.seed}: training on {self.train} ({device})")
        reward = dict(self.arm.reward) or None
        env = make_env(self.train, tcfg.n_actors, device, self.seed, task=tcfg.task, reward=reward)
        result = train(
            env,
            tcfg,
            run_dir=self.run_dir,
            corpus_summary=corpus_summary(self.train, "sdfdag"),
            progress=False,
        )
        del env
        return [self._fly(result, noise, device, say) for noise in self.cfg.noises()]

    def _fly(self, result: Any, noise: float, device: str, say: Say) -> dict[str, Any]:
        """The run's row for one action noise: its final checkpoint flown on every unseen part (and the
        open floor), its mean action at 0, sampled with `noise` times its learned std above."""
        from navi_learner.evaluation.evaluate import CheckpointPolicy

        p = self.cfg.protocol
        name = flown_as(self.arm.spec, noise, self.cfg.train.task)
        trained = CheckpointPolicy(result.final_checkpoint, torch.device(device), noise, p.seed)
        finals: dict[str, Any] = {}
        collisions: dict[str, dict[str, int]] = {}
        flown: dict[str, dict[str, float]] = {}
        for part, corpus in self.unseen.items():
            env = eval_env(corpus, self.cfg, device)
            sites = CollisionSites(env.config) if part == "openarena" else None
            flights = GoalFlights() if part == "openarena" and self.cfg.train.task == "pointgoal" else None
            metrics = evaluate(
                env, trained, p.steps, p.seed, by_scene=part == "openarena", observe=observers(sites, flights)
            )
            metrics.policy = f"{name} seed {self.seed}"
            metrics.per_actor = {}
            finals[part] = asdict(metrics)
            if sites is not None:
                collisions = sites.classify(env, _names(env))
            if flights is not None:
                flown = flights.summary(_names(env))
            say(f"[bench transfer] {name} seed {self.seed} on {part}:\n{comparison_table([metrics])}")
        floor: list[dict[str, Any]] = []
        probe = self.cfg.open_floor
        if self.floors and probe is not None:
            trained.name = f"{name} seed {self.seed}"
            rows = open_floor_probe(trained, open_floor_env(self.floors, probe, device), probe)
            floor = [asdict(r) for r in rows]
            say(f"[bench transfer] {name} seed {self.seed} on the open floors:\n{probe_table(rows)}")
        return {
            "arm": name,
            "trained_arm": self.arm.spec,
            "action_noise": noise,
            "seed": self.seed,
            "checkpoint": str(result.final_checkpoint),
            "steps": result.step_id,
            "train_s": float(result.last_metrics.get("train_s", 0.0)),
            "sps": result.sps,
            "final_by_part": finals,
            "collisions_by_surface": collisions,
            "goal_flights": flown,
            "open_floor": floor,
        }


@dataclass(frozen=True)
class WarmupJob:
    """WARMUP_UPDATES untimed updates of the recipe on a train corpus, run by each worker before its first
    timed run: they put the compiled rollout step and update in the compile cache, so that no run spends
    its budget compiling (the first run on a fresh host would otherwise train about a third fewer steps
    in 200 s than the runs after it)."""

    cfg: TransferConfig
    train: Path
    run_dir: Path

    def __call__(self, device: str, say: Say) -> dict[str, Any]:
        from navi_learner.ppo.train import train

        started = time.perf_counter()
        tcfg = learning_size(self.cfg.train, torch.device(device))
        tcfg = replace(
            tcfg,
            total_steps=WARMUP_UPDATES * tcfg.n_actors * tcfg.rollout_length,
            time_limit_s=0.0,
            checkpoint_every=10**12,
            device=device,
        )
        env = make_env(self.train, tcfg.n_actors, device, tcfg.seed, task=tcfg.task)
        train(
            env,
            tcfg,
            run_dir=self.run_dir,
            corpus_summary=corpus_summary(self.train, "sdfdag"),
            progress=False,
        )
        seconds = time.perf_counter() - started
        say(f"[bench transfer] warm-up on {device}: {WARMUP_UPDATES} untimed updates in {seconds:.0f} s")
        return {"device": device, "updates": WARMUP_UPDATES, "seconds": seconds}


def _names(env: Any) -> tuple[str, ...]:
    from navi_learner.envs.protocol import capabilities

    return capabilities(env).scenes


@dataclass(frozen=True)
class BaselineJob:
    """The task's baselines on one evaluation corpus."""

    part: str
    corpus: Path
    cfg: TransferConfig

    def __call__(self, device: str, say: Say) -> dict[str, Any]:
        env = eval_env(self.corpus, self.cfg, device)
        p = self.cfg.protocol
        out: dict[str, Any] = {}
        rows = []
        for policy in baseline_policies(env, p):
            sites = CollisionSites(env.config) if self.part == "openarena" else None
            goal = self.part == "openarena" and self.cfg.train.task == "pointgoal"
            flights = GoalFlights() if goal else None
            metrics = evaluate(
                env, policy, p.steps, p.seed, by_scene=sites is not None, observe=observers(sites, flights)
            )
            metrics.per_actor = {}
            rows.append(metrics)
            out[policy.name] = asdict(metrics)
            if sites is not None:
                out[policy.name]["collisions_by_surface"] = sites.classify(env, _names(env))
            if flights is not None:
                out[policy.name]["goal_flights"] = flights.summary(_names(env))
        say(f"[bench transfer] baselines on {self.corpus}:\n" + comparison_table(rows))
        return {"part": self.part, "corpus": str(self.corpus), "baselines": out}


def eval_env(corpus: Path, cfg: TransferConfig, device: str) -> Any:
    """An evaluation env of the job's protocol over `corpus`."""
    p = cfg.protocol
    return make_env(corpus, p.actors, device, p.seed, episode_steps=p.episode_steps, task=cfg.train.task)


def _device_worker(args: tuple[str, list[Any]]) -> list[Any]:
    """Run jobs one after another on one device (a process of its own per GPU)."""
    device, jobs = args
    if device.startswith("cuda:"):
        torch.cuda.set_device(torch.device(device))
    return [job(device, say_stderr) for job in jobs]


def run_spread(jobs: list[Any], device: str, gpus: int) -> list[Any]:
    """Every job's result, in order: on `device` in this process, or with gpus > 0 job k on cuda:(k % gpus),
    one process per GPU working through its jobs in turn."""
    if gpus <= 0:
        return [job(device, say_stderr) for job in jobs]
    shares = [(f"cuda:{g}", jobs[g::gpus]) for g in range(gpus)]
    # not a multiprocessing.Pool: its workers are daemons, which may not start the compile processes
    with ProcessPoolExecutor(gpus, multiprocessing.get_context("spawn")) as pool:
        done = list(pool.map(_device_worker, shares))
    out: list[Any] = [None] * len(jobs)
    for g, results in enumerate(done):
        for k, r in enumerate(results):
            out[g + k * gpus] = r
    return out


def median_rows(runs: list[dict[str, Any]], part: str, metrics: tuple[str, ...]) -> dict[str, dict[str, Any]]:
    """Per arm: the median over its seeds of each metric on `part`, and the seeds' values."""
    out: dict[str, dict[str, Any]] = {}
    for arm in dict.fromkeys(r["arm"] for r in runs):
        mine = [r["final_by_part"][part] for r in runs if r["arm"] == arm and part in r["final_by_part"]]
        if mine:
            out[arm] = {
                m: {"median": statistics.median(x[m] for x in mine), "seeds": [x[m] for x in mine]}
                for m in metrics
            }
    return out


def verdict(row: dict[str, Any], baselines: dict[str, Any], task: str) -> bool:
    """The competence bar on one part: explore, collisions <= half the reactive avoider's (<= 0.5 where it
    has none) and coverage >= 1.5x its; point-goal, success >= 0.9, SPL >= 0.8 and fewer collisions per
    episode than the greedy seeker."""
    if task == "pointgoal":
        greedy = baselines["greedy"]
        return bool(
            row["success_rate"] >= 0.9
            and row["spl"] >= 0.8
            and row["collisions_per_episode"] < greedy["collisions_per_episode"]
        )
    reactive = baselines["reactive"]
    r = reactive["collisions_per_1k"]
    bar = 0.5 * r if r > 0 else COLLISION_FLOOR_PER_1K  # evaluate.collision_bar, on result rows
    return bool(
        row["collisions_per_1k"] <= bar and row["coverage_per_1k"] >= 1.5 * reactive["coverage_per_1k"]
    )


def task_metrics(task: str) -> tuple[str, ...]:
    """The metrics the report shows for a task."""
    if task == "pointgoal":
        return ("success_rate", "spl", "collisions_per_episode")
    return ("collisions_per_1k", "coverage_per_1k")


def summarise(runs: list[dict[str, Any]], baselines: dict[str, dict[str, Any]], task: str) -> dict[str, Any]:
    """Per part: per arm the median over seeds (and each seed) of the task's metrics, and per seed
    whether the run clears the bar there; per OpenArena map: per arm the median collisions/1k and
    coverage/1k (or success and SPL), beside the baselines'."""
    metrics = task_metrics(task)
    out: dict[str, Any] = {"parts": {}, "per_map": {}, "surfaces": {}, "open_floor": open_floor_rows(runs)}
    for part, base in baselines.items():
        rows = median_rows(runs, part, metrics)
        for arm, arm_row in rows.items():
            seeds = [r for r in runs if r["arm"] == arm and part in r["final_by_part"]]
            arm_row["competent_seeds"] = sum(verdict(r["final_by_part"][part], base, task) for r in seeds)
            arm_row["seeds_run"] = len(seeds)
        out["parts"][part] = {
            "arms": rows,
            "baselines": {k: {m: v[m] for m in metrics} for k, v in base.items()},
        }
    if "openarena" in baselines:
        maps = sorted(next(iter(baselines["openarena"].values()))["per_scene"])
        for name in maps:
            row: dict[str, Any] = {
                k: {m: v["per_scene"][name][m] for m in metrics} for k, v in baselines["openarena"].items()
            }
            for arm in dict.fromkeys(r["arm"] for r in runs):
                mine = [
                    r["final_by_part"]["openarena"]["per_scene"][name]
                    for r in runs
                    if r["arm"] == arm and "openarena" in r["final_by_part"]
                ]
                if mine:
                    row[arm] = {m: statistics.median(x[m] for x in mine) for m in metrics}
            out["per_map"][name] = row
        for arm in dict.fromkeys(r["arm"] for r in runs):
            kept = [r["collisions_by_surface"].get("all", {}) for r in runs if r["arm"] == arm]
            out["surfaces"][arm] = {
                k: sum(c.get(k, 0) for c in kept) for k in COUNTS if any(k in c for c in kept)
            }  # a count no run kept (results saved before it was counted) stays out of the table
        for name, b in baselines["openarena"].items():
            out["surfaces"][name] = b.get("collisions_by_surface", {}).get("all", {})
        out["flights"] = flight_rows(runs, baselines["openarena"])
    return out


def flight_rows(runs: list[dict[str, Any]], baselines: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Per arm (the median over its seeds of each FLIGHTS value over all the maps; episodes summed) and
    per baseline: how point-goal episodes on the OpenArena maps ended. Empty for explore runs."""
    out: dict[str, dict[str, float]] = {}
    for arm in dict.fromkeys(r["arm"] for r in runs):
        seeds = [r["goal_flights"]["all"] for r in runs if r["arm"] == arm and r.get("goal_flights")]
        if seeds:
            out[arm] = {
                k: sum(s[k] for s in seeds) if k == "episodes" else statistics.median(s[k] for s in seeds)
                for k in FLIGHTS
            }
    for name, b in baselines.items():
        if b.get("goal_flights"):
            out[name] = b["goal_flights"]["all"]
    return out


def open_floor_rows(runs: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, list[float]]]]:
    """Per arm and floor width: each seed's final height (median over its drones) and share on the floor."""
    out: dict[str, dict[str, dict[str, list[float]]]] = {}
    for r in runs:
        for row in r.get("open_floor", []):
            cell = out.setdefault(r["arm"], {}).setdefault(
                f"{row['width']:g}", {"final_height": [], "on_floor": []}
            )
            cell["final_height"].append(row["final_height"])
            cell["on_floor"].append(row["on_floor"])
    return out


def _fmt(x: Any) -> str:
    return "–" if x is None or x != x else f"{x:.3g}" if isinstance(x, float) else str(x)


def report_markdown(result: dict[str, Any]) -> str:
    """report.md: per part the arms' medians against the baselines, the surfaces hit, the maps."""
    s = result["summary"]
    task = result["task"]
    metrics = task_metrics(task)
    lines = ["# navi bench transfer", "", f"{result['device']}, {result['date']}, task {task}, "
             f"{result['config']['budget_s']:.0f} s of training per run, seeds {result['config']['seeds']}", ""]  # fmt: skip
    warm = result.get("warmups", [])
    if warm:
        seconds = ", ".join(f"{w['seconds']:.0f}" for w in warm)
        lines += [
            f"Each worker first ran {warm[0]['updates']} untimed updates (the compile warm-up: {seconds} s).",
            "",
        ]
    for part, p in s["parts"].items():
        lines += [f"## {part}", "", "| policy | " + " | ".join(metrics) + " | competent seeds |"]
        lines += ["| --- |" + " --- |" * (len(metrics) + 1)]
        for arm, row in p["arms"].items():
            cells = [
                f"{_fmt(row[m]['median'])} ({', '.join(_fmt(v) for v in row[m]['seeds'])})" for m in metrics
            ]
            lines.append(
                f"| {arm} | " + " | ".join(cells) + f" | {row['competent_seeds']}/{row['seeds_run']} |"
            )
        for name, row in p["baselines"].items():
            lines.append(f"| {name} | " + " | ".join(_fmt(row[m]) for m in metrics) + " | |")
        lines.append("")
    if s["surfaces"]:
        lines += ["## Collisions on the OpenArena maps by the surface touched (all seeds)", ""]
        lines += [f"pinned: the drone's {PINNED_STEPS}th or later contact step in a row.", ""]
        lines += [
            "| policy | " + " | ".join(COUNTS) + " |",
            "| --- |" + " --- |" * len(COUNTS),
        ]
        for name, row in s["surfaces"].items():
            lines.append(f"| {name} | " + " | ".join(str(row.get(k, "–")) for k in COUNTS) + " |")
        lines.append("")
    if s.get("flights"):
        lines += ["## How point-goal episodes on the OpenArena maps ended (arms: median over seeds)", ""]
        lines += [
            f"near: came within {NEAR_M:g} m of the goal; nearest and final: path length to the goal over the "
            "start's; climb and sink: from the height after the first step (m); speed: m/s (medians over "
            "episodes).",
            "",
            "| policy | " + " | ".join(FLIGHTS) + " |",
            "| --- |" + " --- |" * len(FLIGHTS),
        ]
        for name, row in s["flights"].items():
            lines.append(f"| {name} | " + " | ".join(_fmt(float(row[k])) for k in FLIGHTS) + " |")
        lines.append("")
    if s.get("open_floor"):
        widths = list(next(iter(s["open_floor"].values())))
        lines += ["## Open floors: final height (m) / share on the floor, per seed", ""]
        lines += [
            "| policy | " + " | ".join(f"{w} m" for w in widths) + " |",
            "| --- |" + " --- |" * len(widths),
        ]
        for arm, by_width in s["open_floor"].items():
            cells = [
                ", ".join(f"{h:.2f} / {f:.0%}" for h, f in zip(c["final_height"], c["on_floor"], strict=True))
                for c in (by_width[w] for w in widths)
            ]
            lines.append(f"| {arm} | " + " | ".join(cells) + " |")
        lines.append("")
    if s["per_map"]:
        policies = list(next(iter(s["per_map"].values())))
        lines += [f"## Per OpenArena map ({metrics[0]} / {metrics[1]}, median over seeds)", ""]
        lines += ["| map | " + " | ".join(policies) + " |", "| --- |" + " --- |" * len(policies)]
        for name, row in s["per_map"].items():
            cells = [
                f"{_fmt(row[k][metrics[0]])} / {_fmt(row[k][metrics[1]])}" if k in row else ""
                for k in policies
            ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_transfer(result: dict[str, Any], path: Path) -> str | None:
    """transfer.png: per OpenArena map the task's first two metrics per policy; None, or why not."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed: no transfer.png"
    per_map = result["summary"]["per_map"]
    if not per_map:
        return "no OpenArena maps in this job: no transfer.png"
    metrics = task_metrics(result["task"])[:2]
    maps = list(per_map)
    policies = list(next(iter(per_map.values())))
    fig, axes = plt.subplots(2, 1, figsize=(max(8, len(maps) * 0.35), 8), sharex=True)
    width = 0.8 / len(policies)
    for ax, metric in zip(axes, metrics, strict=True):
        for k, name in enumerate(policies):
            values = [per_map[m].get(name, {}).get(metric, float("nan")) for m in maps]
            ax.bar([i + k * width for i in range(len(maps))], values, width, label=name)
        ax.set_ylabel(metric)
    axes[-1].set_xticks([i + 0.4 - width / 2 for i in range(len(maps))], maps, rotation=90, fontsize=7)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return None


def bench_transfer(
    cfg: TransferConfig,
    out: Path,
    device: str,
    resolution: int,
    root: Path,
    pk3: Path | None,
    say: Say = print,
) -> dict[str, Any]:
    """The whole benchmark; writes and returns result.json's content."""
    if not cfg.arms:
        raise ValueError("name at least one arm")
    for arm in cfg.arms:  # a weight the task does not read fails before any corpus is built
        try:
            reward_config(dict(arm.reward), cfg.train.task)
        except ValueError as err:
            raise ValueError(f"arm {arm.spec!r}: {err}") from err
    if cfg.gpus > 0 and (not device.startswith("cuda") or torch.cuda.device_count() < cfg.gpus):
        raise ValueError(f"--gpus {cfg.gpus} needs that many CUDA devices")
    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    builds, finish = plan_corpora(cfg, root, resolution, pk3, device)
    run_spread(builds, device, cfg.gpus)
    corpora = finish()
    say(f"[bench transfer] corpora ready after {time.perf_counter() - started:.0f} s")
    parts = {part: folder for parts in corpora.unseen.values() for part, folder in parts.items()}
    probe = cfg.open_floor if cfg.train.task == "explore" else None
    floors = build_open_floors(root / "open-floor", probe) if probe is not None else {}
    base_jobs = [BaselineJob(part, folder, cfg) for part, folder in parts.items()]
    run_jobs = [
        RunJob(
            arm,
            seed,
            cfg,
            corpora.train[arm.key],
            corpora.unseen[arm.key],
            out / "runs" / f"{arm.run_key}-seed{seed}",
            floors,
        )
        for seed in cfg.seeds
        for arm in cfg.arms
        if arm.key in corpora.train
    ]
    warm_jobs = (
        [WarmupJob(cfg, run_jobs[0].train, out / "runs" / f"warmup-{k}") for k in range(max(1, cfg.gpus))]
        if run_jobs
        else []
    )  # one per worker, ahead of its first run: any `gpus` consecutive jobs go one to each GPU
    done = run_spread([*base_jobs, *warm_jobs, *run_jobs], device, cfg.gpus)
    baselines = {d["part"]: d["baselines"] for d in done[: len(base_jobs)]}
    warmups = list(done[len(base_jobs) : len(base_jobs) + len(warm_jobs)])
    runs = [row for rows in done[len(base_jobs) + len(warm_jobs) :] for row in rows]
    result: dict[str, Any] = {
        "device": (torch.cuda.get_device_name() if device.startswith("cuda") else "cpu")
        + (f" x {cfg.gpus} (one run per GPU at a time)" if cfg.gpus > 0 else ""),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "task": cfg.train.task,
        "resolution": resolution,
        "config": jsonable(asdict(replace(cfg, seeds=list(cfg.seeds)))),  # type: ignore[arg-type]
        "scenes": corpora.scenes,
        "notes": corpora.notes,
        "baselines": baselines,
        "warmups": warmups,
        "runs": runs,
        "summary": summarise(runs, baselines, cfg.train.task),
        "wall_s": time.perf_counter() - started,
    }
    why_not = plot_transfer(result, out / "transfer.png")
    if why_not:
        result["notes"].append(why_not)
    (out / "result.json").write_text(json.dumps(jsonable(result), indent=1))
    (out / "report.md").write_text(report_markdown(result))
    return result
