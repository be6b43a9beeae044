"""Learner commands: `navi train`, `infer`, `evaluate`, `compare`, `export` and `run`, and the helpers the
`models` and `bench` groups share with them (the env and the TrainConfig a command builds).
Module-level imports: typer and the standard library only."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer

from navi.commands.common import (
    DEFAULT_CORPUS,
    MODELS_DIR,
    UNSEEN_CORPUS,
    CorpusOpt,
    DeviceOpt,
    EnvOpt,
    JsonOpt,
    ResumeOpt,
    SeedOpt,
    TaskOpt,
    check_choice,
    fail,
    pick_device,
)
from navi.commands.options import Settings, config_options
from navi_learner.config import RunBudget, TrainConfig

if TYPE_CHECKING:
    from navi_learner.evaluation.baselines import EvalPolicy
    from navi_learner.evaluation.evaluate import EvalMetrics

EngineOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--engine",
        help="KEY=VALUE: replace an EngineConfig field of a fresh engine (repeatable), e.g. --engine "
        "patch_el=16 --engine encoder_heads=2.",
    ),
]


NprocOpt = Annotated[
    int,
    typer.Option(
        "--nproc",
        min=1,
        help="Data-parallel ranks on this machine, one per GPU (runs the command again through torchrun "
        "--standalone --nproc-per-node N; ignored inside torchrun).",
    ),
]


ObstaclesOpt = Annotated[
    int,
    typer.Option(
        "--obstacles",
        min=0,
        max=64,
        help="Scripted moving obstacles per actor (drone env; traced, felt by physics, their collisions "
        "counted).",
    ),
]


SquadOpt = Annotated[
    int,
    typer.Option(
        "--squad",
        min=0,
        max=64,
        help="Other drones as obstacles: squads of this many actors share a scene, see and collide with "
        "each other (0: off; must divide the actors).",
    ),
]


def build_env(
    env_kind: str,
    corpus: Path | None,
    n_actors: int,
    device: str,
    seed: int,
    rank: int = 0,
    world: int = 1,
    obstacles: int = 0,
    squad: int = 0,
    task: str = "explore",
    rank_scenes: str = TrainConfig.rank_scenes,
    episode_steps: int = 0,
) -> Any:
    """The environment for a command (a data-parallel rank: every scene, or its share with `rank_scenes`
    "share"; episodes of `episode_steps` where > 0, else the task's own), or exit 2."""
    from navi_env.config import TASKS
    from navi_learner.envs.factory import EnvUnavailable, make_env

    kind: Literal["sdfdag", "toy"] = (
        "toy" if check_choice(env_kind, ("sdfdag", "toy"), "--env") == "toy" else "sdfdag"
    )
    try:
        return make_env(
            corpus if corpus is not None or kind == "toy" else DEFAULT_CORPUS,
            n_actors,
            device,
            seed,
            kind,
            rank=rank,
            world=world,
            obstacles=obstacles,
            squad=squad,
            task=check_choice(task, TASKS, "--task"),
            rank_scenes=rank_scenes,  # checked by train_config and by the corpus loader
            episode_steps=episode_steps,
        )
    except (EnvUnavailable, ValueError) as err:
        raise fail(str(err)) from err


def train_config(settings: Settings, device: str, engine_items: list[str] | None = None) -> TrainConfig:
    """The TrainConfig of a command's generated options on `device` (its --device, resolved), with the
    temporal core, observation storage and task checked; `engine_items` (--engine KEY=VALUE) replace
    fields of the engine."""
    from navi_env.config import TASKS
    from navi_env.corpus.folder import RANK_SCENES
    from navi_learner.config import OBS_STORAGE, TEMPORAL_CORES, engine_overrides

    cfg: TrainConfig = settings.config()
    check_choice(cfg.engine.temporal_core, TEMPORAL_CORES, "--temporal-core")
    check_choice(cfg.obs_dtype, OBS_STORAGE, "--obs-storage")
    check_choice(cfg.task, TASKS, "--task")
    check_choice(cfg.rank_scenes, RANK_SCENES, "--rank-scenes")
    try:
        overrides = engine_overrides(engine_items or [])
    except ValueError as err:
        raise fail(str(err)) from err
    return replace(cfg, device=device, engine=replace(cfg.engine, **overrides))


TRAIN_OPTIONS = (
    "n_actors",
    "temporal_core",
    "rollout_length",
    "ppo_epochs",
    "lr",
    "target_kl",
    "mean_bound_coef",
    "compile_rollout",
    "compile_update",
    "update_graphs",
    "tf32",
    "total_steps",
    "time_limit_s",
    "checkpoint_every",
    "device",
    "seed",
    "compile",
    "obs_dtype",
    "max_minibatch",
    "task",
    "rank_scenes",
    "init_from",
)
"""The TrainConfig settings `navi train` takes as options."""

COMMAND_DEVICE = {"device": "auto"}
"""A command's --device defaults to auto (cuda where available), resolved before the config is built."""


def resume_choice(checkpoint: Path | None, fresh: bool, cfg: TrainConfig) -> tuple[Path | None, TrainConfig]:
    """Explicit --checkpoint, else artifacts/models/latest.pt when compatible (same temporal core and
    task); the engine comes from it."""
    from dataclasses import replace

    from navi_learner.config import EngineConfig
    from navi_learner.serving.checkpoint import CheckpointError, read_meta

    path = checkpoint if checkpoint is not None else (None if fresh else MODELS_DIR / "latest.pt")
    if path is None or (checkpoint is None and not path.is_file()):
        return None, cfg
    try:
        meta = read_meta(path)
    except CheckpointError as err:
        raise fail(str(err)) from err
    if meta.temporal_core != cfg.engine.temporal_core:
        if checkpoint is not None:
            raise fail(f"{path} was trained with --temporal-core {meta.temporal_core}")
        typer.echo(
            f"note: {path} uses {meta.temporal_core}; starting a fresh {cfg.engine.temporal_core} run",
            err=True,
        )
        return None, cfg
    task = str(meta.config.get("task", "explore"))
    if task != cfg.task:
        if checkpoint is not None:
            raise fail(f"{path} was trained with --task {task}")
        typer.echo(f"note: {path} learned {task}; starting a fresh {cfg.task} run", err=True)
        return None, cfg
    typer.echo(f"resuming from {path} (step {meta.step_id:,})", err=True)
    return path, replace(cfg, engine=EngineConfig.from_dict(meta.config["engine"]))


def print_metrics(
    rows: list[EvalMetrics],
    as_json: bool,
    collisions: dict[str, dict[str, int]] | None = None,
    flights: dict[str, dict[str, float]] | None = None,
) -> None:
    """One JSON object, or a markdown table (under it each trained policy's mean_outside_line and
    contact_line); with `collisions` (CollisionSites.classify rows) also the collision table, under
    "collisions" in the JSON, and with `flights` (GoalFlights.summary rows) the point-goal episodes'
    table, under "goal_flights"."""
    from navi_learner.evaluation.collisions import collision_table
    from navi_learner.evaluation.evaluate import comparison_table, contact_line, jsonable, mean_outside_line
    from navi_learner.evaluation.goal_flights import flight_table

    if as_json:
        extra: dict[str, object] = {} if collisions is None else {"collisions": collisions}
        extra |= {} if flights is None else {"goal_flights": flights}
        typer.echo(json.dumps(jsonable({"results": [asdict(r) for r in rows], **extra})))
    else:
        tables = [comparison_table(rows)]
        tables += [line for line in map(mean_outside_line, rows) if line]
        trained = [r for r in rows if r.mean_outside]  # the trained policies (baselines have no means)
        tables += [line for line in (contact_line(r, r.policy) for r in trained) if line]
        tables += [] if collisions is None else [collision_table(collisions)]
        tables += [] if flights is None else [flight_table(flights)]
        typer.echo("\n\n".join(tables))


BASELINES = ("random", "reactive", "greedy", "oracle")
"""Policies `evaluate --policy` and `compare` know by name; greedy and oracle fly point-goal episodes."""


def eval_policy(spec: str, device: str, seed: int, noise: float | None, env: object = None) -> EvalPolicy:
    """'random', 'reactive' (tuned to env's horizon and ray pattern), 'greedy' or 'oracle' (point-goal),
    or a checkpoint path / registry version, flown with `noise` times its learned std (0: its mean action;
    None: as its task flies, ACTION_NOISE), the draws seeded by `seed`."""
    import torch

    from navi_learner.evaluation.baselines import RandomPolicy, goal_seeker_for_env, reactive_for_env
    from navi_learner.evaluation.evaluate import CheckpointPolicy
    from navi_learner.serving.checkpoint import CheckpointError
    from navi_learner.serving.registry import ModelRegistry, RegistryError

    if spec == "random":
        return RandomPolicy(seed)
    if spec == "reactive":
        return reactive_for_env(env)
    if spec in ("greedy", "oracle"):
        try:
            return goal_seeker_for_env(spec, env)
        except ValueError as err:
            raise fail(f"--policy {spec}: {err}") from err
    path = Path(spec)
    if not path.is_file():
        try:
            path = ModelRegistry(MODELS_DIR).path(spec)
        except RegistryError as err:
            raise fail(
                f"{spec} is neither {', '.join(BASELINES)}, a checkpoint file nor a registry version"
            ) from err
    try:
        return CheckpointPolicy(path, torch.device(device), noise, seed)
    except CheckpointError as err:
        raise fail(str(err)) from err


def checkpoint_task(spec: str) -> str:
    """The task a checkpoint file or registry version learned (explore where it says none or is not
    found: the policy loader reports a missing checkpoint)."""
    from navi_learner.serving.checkpoint import CheckpointError, read_meta
    from navi_learner.serving.registry import ModelRegistry, RegistryError

    path = Path(spec)
    try:
        if not path.is_file():
            path = ModelRegistry(MODELS_DIR).path(spec)
        return str(read_meta(path).config.get("task", "explore"))
    except (CheckpointError, RegistryError, OSError):
        return "explore"


PANEL = "Learner"
app = typer.Typer()
"""Merged into the root: its commands are `navi train`, `navi run`, ..."""


@app.command(rich_help_panel=PANEL)
@config_options(TrainConfig(), TRAIN_OPTIONS, defaults=COMMAND_DEVICE)
def train(
    *,
    corpus: CorpusOpt = None,
    settings: Settings,
    checkpoint: ResumeOpt = None,
    fresh: Annotated[
        bool, typer.Option("--fresh", help="Do not resume from artifacts/models/latest.pt.")
    ] = False,
    env: EnvOpt = "sdfdag",
    nproc: NprocOpt = 1,
    obstacles: ObstaclesOpt = 0,
    squad: SquadOpt = 0,
    engine: EngineOpt = None,
) -> None:
    """Train with PPO in-process with the environment; Ctrl+C saves a checkpoint first. Under torchrun
    (or with --nproc N) every rank trains its own actors on its own device with synchronous
    data-parallel PPO; --actors is per rank."""
    import torch

    from navi_learner.config import StorageError, default_actors, engine_overrides
    from navi_learner.envs.factory import corpus_summary
    from navi_learner.ppo import dist
    from navi_learner.ppo.learner import InitError, init_engine
    from navi_learner.ppo.train import train as run_train
    from navi_learner.serving.registry import ModelRegistry

    if nproc > 1 and not dist.launched():
        raise typer.Exit(dist.relaunch(nproc, dist.strip_option(sys.argv[1:], "--nproc")))
    try:
        d, dev = dist.setup(pick_device(settings["device"]))
    except ValueError as err:
        raise fail(str(err)) from err
    signals = dist.StopSignals().install() if d.active else None
    try:
        cfg = train_config(settings, dev, engine)
        if cfg.init_from and checkpoint is not None:
            raise fail("--init-from starts a fresh run from a checkpoint's weights; --checkpoint resumes one")
        if cfg.init_from:  # the checkpoint's engine, --engine's fields on top
            overrides = engine_overrides(engine or [])
            cfg = replace(cfg, engine=init_engine(cfg.init_from, cfg.engine.temporal_core, overrides))
        resume, cfg = (None, cfg) if cfg.init_from else resume_choice(checkpoint, fresh, cfg)
        if resume is not None and engine:
            typer.echo(f"note: --engine is ignored: the engine comes from {resume}", err=True)
        n = cfg.n_actors or default_actors(torch.device(dev))
        environment = build_env(
            env,
            corpus,
            n,
            dev,
            cfg.seed + d.rank,
            d.rank,
            d.world,
            obstacles,
            squad,
            cfg.task,
            cfg.rank_scenes,
        )
        summary = corpus_summary(corpus or DEFAULT_CORPUS, "toy" if env == "toy" else "sdfdag")
        result = run_train(
            environment,
            cfg,
            resume_from=resume,
            registry=ModelRegistry(MODELS_DIR) if d.main else None,
            corpus_summary=summary,
            dist=d,
            should_stop=None if signals is None else signals.requested,
        )
    except (dist.DistError, StorageError, InitError) as err:
        raise fail(str(err)) from err
    finally:
        dist.shutdown(d)
    if not d.main:
        dist.leave(d)  # rank 0 reports (and exits 130 when interrupted)
        return
    typer.echo(
        json.dumps(
            {
                "run_id": result.run_id,
                "checkpoint": str(result.final_checkpoint),
                "report": str(result.report),
                "steps": result.step_id,
                "reward_ema": result.reward_ema,
                "sps": round(result.sps, 1),
                "promoted": result.promoted,
                "interrupted": result.interrupted,
            }
        )
    )
    dist.leave(d, 130 if result.interrupted else 0)
    if result.interrupted:
        raise typer.Exit(130)


@app.command(rich_help_panel=PANEL)
def infer(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Checkpoint to run.")],
    deterministic: Annotated[
        bool,
        typer.Option("--deterministic", help="Use the mean action (default: sampled with the learned std)."),
    ] = False,
    total_steps: Annotated[int, typer.Option("--total-steps", help="Batched steps to run.")] = 1000,
    corpus: CorpusOpt = None,
    actors: Annotated[int, typer.Option("--actors", help="Parallel actors.")] = 4,
    device: DeviceOpt = "auto",
    seed: SeedOpt = 0,
    env: EnvOpt = "sdfdag",
    as_json: JsonOpt = False,
    remote: Annotated[
        bool,
        typer.Option(
            "--remote",
            help="Fly the drones of a `navi serve env` over Zenoh (NAVI_ZENOH_CONNECT) instead of an "
            "in-process env; --actors of its drones are driven.",
        ),
    ] = False,
) -> None:
    """Run a checkpoint (no PPO) in-process, or against a remote env service, and report its metrics."""
    from navi_learner.evaluation.evaluate import evaluate

    dev = pick_device(device)
    if remote:
        from navi_learner.envs.remote import RemoteEnv, RemoteEnvError

        policy = eval_policy(str(checkpoint), dev, seed, 0.0 if deterministic else 1.0)
        try:
            remote_env = RemoteEnv(actors, dev)
            metrics = evaluate(remote_env, policy, total_steps, seed, progress=True)
        except RemoteEnvError as err:
            raise fail(str(err)) from err
        print_metrics([metrics], as_json)
        return
    environment = build_env(env, corpus, actors, dev, seed, task=checkpoint_task(str(checkpoint)))
    policy = eval_policy(str(checkpoint), dev, seed, 0.0 if deterministic else 1.0, environment)
    print_metrics([evaluate(environment, policy, total_steps, seed, progress=True)], as_json)


@app.command(name="evaluate", rich_help_panel=PANEL)
def evaluate_cmd(
    checkpoint: Annotated[str | None, typer.Argument(help="Checkpoint file or registry version.")] = None,
    policy: Annotated[
        str | None,
        typer.Option("--policy", help="Baseline instead: random, reactive, greedy or oracle (point-goal)."),
    ] = None,
    corpus: CorpusOpt = None,
    steps: Annotated[int, typer.Option("--steps", help="Batched steps.")] = 1000,
    actors: Annotated[int, typer.Option("--actors", help="Parallel actors.")] = 4,
    device: DeviceOpt = "auto",
    seed: SeedOpt = 0,
    env: EnvOpt = "sdfdag",
    obstacles: ObstaclesOpt = 0,
    squad: SquadOpt = 0,
    as_json: JsonOpt = False,
    task: Annotated[
        str | None,
        typer.Option(
            "--task",
            help="explore or pointgoal (default: the task the checkpoint learned; explore for a baseline).",
        ),
    ] = None,
    episode_steps: Annotated[
        int,
        typer.Option(
            "--episode-steps",
            min=0,
            help="Episode length in steps (drone env; 0: the task's own). The benchmarks' protocol is 500.",
        ),
    ] = 0,
    action_noise: Annotated[
        float | None,
        typer.Option(
            "--action-noise",
            min=0.0,
            help="A checkpoint's actions sampled with this many times its learned std, 0 its mean action "
            "(default: as its task is evaluated everywhere: explore 1, point-goal 0).",
        ),
    ] = None,
    collisions: Annotated[
        bool,
        typer.Option(
            "--collisions",
            help="Also count the collisions per scene (drone env): the surface touched (floor, ceiling, wall, "
            "slope), thin geometry behind it, pinned (the 10th or later contact step in a row), pushing (pinned "
            "while commanding into the nearest surface in view) and unseen (no ray of the view showed it).",
        ),
    ] = False,
    goal_flights: Annotated[
        bool,
        typer.Option(
            "--goal-flights",
            help="Point-goal: also say per scene how the episodes ended (success, came within 2 m, nearest "
            "and final path length over the start's, climb and sink from the first step's height, speed).",
        ),
    ] = False,
) -> None:
    """Evaluate a checkpoint or a baseline: return, collisions (with moving obstacles among them),
    clearance, coverage, distance, starvation; point-goal episodes add success, SPL, soft SPL,
    collisions per episode and time to goal."""
    from navi_learner.envs.protocol import capabilities
    from navi_learner.evaluation.collisions import CollisionSites
    from navi_learner.evaluation.evaluate import evaluate, observers
    from navi_learner.evaluation.goal_flights import GoalFlights

    if (checkpoint is None) == (policy is None):
        raise typer.BadParameter(f"give exactly one of CHECKPOINT or --policy {'|'.join(BASELINES)}")
    if policy is not None:
        check_choice(policy, BASELINES, "--policy")
    dev = pick_device(device)
    chosen_task = task or (checkpoint_task(checkpoint) if checkpoint is not None else "explore")
    environment = build_env(
        env,
        corpus,
        actors,
        dev,
        seed,
        obstacles=obstacles,
        squad=squad,
        task=chosen_task,
        episode_steps=episode_steps,
    )
    chosen = eval_policy(policy or str(checkpoint), dev, seed, action_noise, environment)
    config = getattr(environment, "config", None)
    if collisions and config is None:
        raise typer.BadParameter("--collisions needs the drone env (--env sdfdag)")
    if goal_flights and (config is None or chosen_task != "pointgoal"):
        raise typer.BadParameter(
            "--goal-flights needs point-goal episodes of the drone env (--task pointgoal)"
        )
    sites = CollisionSites(config) if collisions else None
    flights = GoalFlights() if goal_flights else None
    metrics = evaluate(environment, chosen, steps, seed, progress=True, observe=observers(sites, flights))
    scenes = capabilities(environment).scenes
    table = None if sites is None else sites.classify(environment, scenes)
    print_metrics([metrics], as_json, table, None if flights is None else flights.summary(scenes))


@app.command(rich_help_panel=PANEL)
def compare(
    policies: Annotated[
        list[str],
        typer.Argument(
            help="Checkpoints, registry versions, random, reactive, greedy or oracle (point-goal)."
        ),
    ],
    corpus: CorpusOpt = None,
    steps: Annotated[int, typer.Option("--steps", help="Batched steps per policy.")] = 1000,
    actors: Annotated[int, typer.Option("--actors", help="Parallel actors.")] = 4,
    device: DeviceOpt = "auto",
    seed: SeedOpt = 0,
    env: EnvOpt = "sdfdag",
    as_json: JsonOpt = False,
    task: TaskOpt = "explore",
) -> None:
    """Evaluate several policies on the same scenes, spawns and seeds (one task for all)."""
    from navi_learner.evaluation.evaluate import evaluate

    dev = pick_device(device)
    rows = []
    for spec in policies:
        environment = build_env(env, corpus, actors, dev, seed, task=task)
        chosen = eval_policy(spec, dev, seed, None, environment)
        rows.append(evaluate(environment, chosen, steps, seed, progress=True))
    print_metrics(rows, as_json)


@app.command(rich_help_panel=PANEL)
def export(
    checkpoint: Annotated[Path, typer.Argument(help="Checkpoint to export.")],
    onnx: Annotated[Path, typer.Option("--onnx", help="Output .onnx file.")],
) -> None:
    """Export the step-mode policy (obs + recurrent state in; action, value, state out) to ONNX."""
    from navi_learner.serving.checkpoint import CheckpointError
    from navi_learner.serving.export import ExportUnavailable, export_onnx

    try:
        typer.echo(str(export_onnx(checkpoint, onnx)))
    except (ExportUnavailable, CheckpointError) as err:
        raise fail(str(err)) from err


@app.command(name="run", rich_help_panel=PANEL)
@config_options(RunBudget(), ("budget_s", "eval_every_s", "n_actors", "cpu_steps"))
def run_cmd(
    *,
    corpus: Annotated[
        Path, typer.Option("--corpus", help="Training corpus (procedural seed 0, built when missing).")
    ] = DEFAULT_CORPUS,
    unseen: Annotated[
        Path,
        typer.Option(
            "--unseen", help="Unseen corpus for evaluation (procedural seed 1000, built when missing)."
        ),
    ] = UNSEEN_CORPUS,
    settings: Settings,
    device: DeviceOpt = "auto",
    seed: SeedOpt = 0,
    task: TaskOpt = "explore",
    real_maps: Annotated[
        bool,
        typer.Option(
            "--real-maps/--no-real-maps",
            help="Where the OpenArena maps are on the machine ($NAVI_OPENARENA_PK3, or where "
            "tests/data/fetch_openarena.sh puts them), also judge the drone on their held-out fifth.",
        ),
    ] = True,
) -> None:
    """The main job: build the corpora, train (CUDA: until competent on unseen scenes or the budget; CPU:
    fine-tune the task's shipped reference checkpoint), promote, evaluate against random and reactive on unseen
    scenes (--task pointgoal: point-goal episodes, compared with random, greedy and oracle); where
    the OpenArena maps are present, also on real maps never seen."""
    from navi_env.config import TASKS
    from navi_env.corpus.openarena import default_pk3
    from navi_learner.evaluation.main_job import MainJobConfig, MainJobError, main_job

    dev = pick_device(device)
    task = check_choice(task, TASKS, "--task")
    job = MainJobConfig(
        corpus=corpus,
        unseen=unseen,
        models_dir=MODELS_DIR,
        device=dev,
        seed=seed,
        **asdict(settings.config()),
        task=task,
        openarena=default_pk3() if real_maps else None,
    )
    try:
        report = main_job(job)
    except MainJobError as err:
        raise fail(str(err)) from err
    typer.echo(f"report: {report}")
