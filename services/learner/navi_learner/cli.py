"""`navi` sub-commands of navi_learner (registered by navi.cli): train, infer, evaluate, compare,
models, export, run, and `bench train`. Module-level imports: typer and the standard library only."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer

if TYPE_CHECKING:
    from navi_learner.baselines import EvalPolicy
    from navi_learner.config import TrainConfig
    from navi_learner.evaluate import EvalMetrics

PANEL = "Learner"
MODELS_DIR = Path("artifacts/models")
RUNS_DIR = Path("artifacts/runs")
DEFAULT_CORPUS = Path("artifacts/corpus/default")
UNSEEN_CORPUS = Path("artifacts/corpus/unseen")

EnvOpt = Annotated[str, typer.Option("--env", help="Environment: sdfdag (the drone env) or toy (tests).")]
CorpusOpt = Annotated[Path | None, typer.Option("--corpus", help="Corpus folder of .gmdag scenes.")]
DeviceOpt = Annotated[str, typer.Option("--device", help="Torch device: auto, cpu, cuda, cuda:N.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed for torch and the environment.")]
CoreOpt = Annotated[str, typer.Option("--temporal-core", help="Temporal core: mamba2, gru or mambapy.")]
ObsStorageOpt = Annotated[
    str,
    typer.Option(
        "--obs-storage",
        help="Rollout observations: compact (3 bytes per ray, the drone env's DistanceMatrix v2), float32 "
        "(12 bytes, any env) or auto (compact where the env allows).",
    ),
]
MaxMinibatchOpt = Annotated[
    int, typer.Option("--max-minibatch", min=1, help="Most samples per PPO minibatch (GPU memory).")
]


def fail(message: str) -> typer.Exit:
    """Print a one-line error to stderr; the caller raises the returned Exit(2)."""
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def pick_device(device: str) -> str:
    """'auto' -> cuda when available, else cpu; anything else is checked."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise fail(f"device {device} requested but CUDA is not available")
    if not (device == "cpu" or device.startswith("cuda")):
        raise fail(f"unknown device {device!r}; use auto, cpu, cuda or cuda:N")
    return device


def check_choice(value: str, choices: tuple[str, ...], what: str) -> str:
    """Validate an enumerated option."""
    if value not in choices:
        raise typer.BadParameter(f"{what} must be one of {', '.join(choices)}, got {value!r}")
    return value


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
) -> Any:
    """The environment for a command (a data-parallel rank: its share of the scenes), or exit 2."""
    from navi_learner.envs import EnvUnavailable, make_env

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
        )
    except (EnvUnavailable, ValueError) as err:
        raise fail(str(err)) from err


def train_config(
    actors: int,
    core: str,
    rollout: int,
    epochs: int,
    lr: float,
    total: int,
    every: int,
    device: str,
    seed: int,
    obs_storage: str = "auto",
    max_minibatch: int = 8_192,
    compile_encoder: bool = True,
) -> TrainConfig:
    """TrainConfig from CLI options (0 keeps a default)."""
    from navi_learner.config import OBS_STORAGE, TEMPORAL_CORES, EngineConfig, PPOConfig, TrainConfig

    name = check_choice(core, TEMPORAL_CORES, "--temporal-core")
    check_choice(obs_storage, OBS_STORAGE, "--obs-storage")
    engine = EngineConfig(
        temporal_core="gru" if name == "gru" else "mambapy" if name == "mambapy" else "mamba2"
    )
    return TrainConfig(
        n_actors=actors,
        rollout_length=rollout,
        total_steps=total,
        checkpoint_every=every,
        device=device,
        seed=seed,
        compile=compile_encoder,
        obs_dtype=obs_storage,
        engine=engine,
        ppo=PPOConfig(lr=lr, ppo_epochs=epochs, max_minibatch=max_minibatch),
    )


def resume_choice(checkpoint: Path | None, fresh: bool, cfg: TrainConfig) -> tuple[Path | None, TrainConfig]:
    """Explicit --checkpoint, else artifacts/models/latest.pt when compatible; the engine comes from it."""
    from dataclasses import replace

    from navi_learner.checkpoint import CheckpointError, read_meta
    from navi_learner.config import EngineConfig

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
    typer.echo(f"resuming from {path} (step {meta.step_id:,})", err=True)
    return path, replace(cfg, engine=EngineConfig.from_dict(meta.config["engine"]))


def print_metrics(rows: list[EvalMetrics], as_json: bool) -> None:
    """One JSON object, or a markdown table."""
    from navi_learner.evaluate import comparison_table, jsonable

    if as_json:
        typer.echo(json.dumps({"results": jsonable([asdict(r) for r in rows])}))
    else:
        typer.echo(comparison_table(rows))


def eval_policy(spec: str, device: str, seed: int, deterministic: bool, env: object = None) -> EvalPolicy:
    """'random', 'reactive' (tuned to env's horizon and ray pattern), or a checkpoint path / registry version."""
    import torch

    from navi_learner.baselines import RandomPolicy, reactive_for_env
    from navi_learner.checkpoint import CheckpointError
    from navi_learner.evaluate import CheckpointPolicy
    from navi_learner.registry import ModelRegistry, RegistryError

    if spec == "random":
        return RandomPolicy(seed)
    if spec == "reactive":
        return reactive_for_env(env)
    path = Path(spec)
    if not path.is_file():
        try:
            path = ModelRegistry(MODELS_DIR).path(spec)
        except RegistryError as err:
            raise fail(
                f"{spec} is neither random, reactive, a checkpoint file nor a registry version"
            ) from err
    try:
        return CheckpointPolicy(path, torch.device(device), deterministic)
    except CheckpointError as err:
        raise fail(str(err)) from err


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add this package's commands to the root app and the `bench` group."""
    models = typer.Typer(help="The model registry (artifacts/models).", no_args_is_help=True)

    @app.command(rich_help_panel=PANEL)
    def train(
        corpus: CorpusOpt = None,
        actors: Annotated[
            int, typer.Option("--actors", help="Parallel actors (0: 4 on CPU, 4096 on CUDA).")
        ] = 0,
        temporal_core: CoreOpt = "mamba2",
        rollout_length: Annotated[
            int, typer.Option("--rollout-length", help="Steps per rollout (0: 512, capped by memory).")
        ] = 0,
        ppo_epochs: Annotated[int, typer.Option("--ppo-epochs", help="PPO epochs per rollout.")] = 1,
        lr: Annotated[float, typer.Option("--lr", help="Learning rate.")] = 5e-4,
        total_steps: Annotated[int, typer.Option("--total-steps", help="Env-step budget.")] = 1_000_000,
        time_limit: Annotated[
            float, typer.Option("--time-limit-s", min=0.0, help="Training-seconds budget (0: none).")
        ] = 0.0,
        checkpoint_every: Annotated[
            int, typer.Option("--checkpoint-every", help="Env steps between checkpoints.")
        ] = 25_000,
        checkpoint: Annotated[
            Path | None, typer.Option("--checkpoint", help="Resume from this checkpoint.")
        ] = None,
        fresh: Annotated[
            bool, typer.Option("--fresh", help="Do not resume from artifacts/models/latest.pt.")
        ] = False,
        device: DeviceOpt = "auto",
        seed: SeedOpt = 0,
        env: EnvOpt = "sdfdag",
        compile_encoder: Annotated[
            bool, typer.Option("--compile/--no-compile", help="torch.compile the encoder on CUDA.")
        ] = True,
        nproc: NprocOpt = 1,
        obstacles: ObstaclesOpt = 0,
        squad: SquadOpt = 0,
        obs_storage: ObsStorageOpt = "auto",
        max_minibatch: MaxMinibatchOpt = 8_192,
    ) -> None:
        """Train with PPO in-process with the environment; Ctrl+C saves a checkpoint first. Under torchrun
        (or with --nproc N) every rank trains its own actors on its own device with synchronous
        data-parallel PPO; --actors is per rank."""
        from dataclasses import replace

        import torch

        from navi_learner import dist
        from navi_learner.config import StorageError, default_actors
        from navi_learner.envs import corpus_summary
        from navi_learner.registry import ModelRegistry
        from navi_learner.train import train as run_train

        if nproc > 1 and not dist.launched():
            raise typer.Exit(dist.relaunch(nproc, dist.strip_option(sys.argv[1:], "--nproc")))
        try:
            d, dev = dist.setup(pick_device(device))
        except ValueError as err:
            raise fail(str(err)) from err
        signals = dist.StopSignals().install() if d.active else None
        try:
            cfg = train_config(
                actors,
                temporal_core,
                rollout_length,
                ppo_epochs,
                lr,
                total_steps,
                checkpoint_every,
                dev,
                seed,
                obs_storage,
                max_minibatch,
                compile_encoder,
            )
            resume, cfg = resume_choice(checkpoint, fresh, replace(cfg, time_limit_s=time_limit))
            n = cfg.n_actors or default_actors(torch.device(dev))
            environment = build_env(env, corpus, n, dev, seed + d.rank, d.rank, d.world, obstacles, squad)
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
        except (dist.DistError, StorageError) as err:
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
        deterministic: Annotated[bool, typer.Option("--deterministic", help="Use the mean action.")] = False,
        total_steps: Annotated[int, typer.Option("--total-steps", help="Batched steps to run.")] = 1000,
        corpus: CorpusOpt = None,
        actors: Annotated[int, typer.Option("--actors", help="Parallel actors.")] = 4,
        device: DeviceOpt = "auto",
        seed: SeedOpt = 0,
        env: EnvOpt = "sdfdag",
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
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
        from navi_learner.evaluate import evaluate

        dev = pick_device(device)
        if remote:
            from navi_learner.remote_env import RemoteEnv, RemoteEnvError

            policy = eval_policy(str(checkpoint), dev, seed, deterministic)
            try:
                metrics = evaluate(RemoteEnv(actors, dev), policy, total_steps, seed, progress=True)
            except RemoteEnvError as err:
                raise fail(str(err)) from err
            print_metrics([metrics], as_json)
            return
        environment = build_env(env, corpus, actors, dev, seed)
        policy = eval_policy(str(checkpoint), dev, seed, deterministic, environment)
        print_metrics([evaluate(environment, policy, total_steps, seed, progress=True)], as_json)

    @app.command(name="evaluate", rich_help_panel=PANEL)
    def evaluate_cmd(
        checkpoint: Annotated[str | None, typer.Argument(help="Checkpoint file or registry version.")] = None,
        policy: Annotated[
            str | None, typer.Option("--policy", help="Baseline instead: random or reactive.")
        ] = None,
        corpus: CorpusOpt = None,
        steps: Annotated[int, typer.Option("--steps", help="Batched steps.")] = 1000,
        actors: Annotated[int, typer.Option("--actors", help="Parallel actors.")] = 4,
        device: DeviceOpt = "auto",
        seed: SeedOpt = 0,
        env: EnvOpt = "sdfdag",
        obstacles: ObstaclesOpt = 0,
        squad: SquadOpt = 0,
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    ) -> None:
        """Evaluate a checkpoint or a baseline: return, collisions (with moving obstacles among them),
        clearance, coverage, distance, starvation."""
        from navi_learner.evaluate import evaluate

        if (checkpoint is None) == (policy is None):
            raise typer.BadParameter("give exactly one of CHECKPOINT or --policy random|reactive")
        if policy is not None:
            check_choice(policy, ("random", "reactive"), "--policy")
        dev = pick_device(device)
        environment = build_env(env, corpus, actors, dev, seed, obstacles=obstacles, squad=squad)
        chosen = eval_policy(policy or str(checkpoint), dev, seed, True, environment)
        print_metrics([evaluate(environment, chosen, steps, seed, progress=True)], as_json)

    @app.command(rich_help_panel=PANEL)
    def compare(
        policies: Annotated[
            list[str], typer.Argument(help="Checkpoints, registry versions, random or reactive.")
        ],
        corpus: CorpusOpt = None,
        steps: Annotated[int, typer.Option("--steps", help="Batched steps per policy.")] = 1000,
        actors: Annotated[int, typer.Option("--actors", help="Parallel actors.")] = 4,
        device: DeviceOpt = "auto",
        seed: SeedOpt = 0,
        env: EnvOpt = "sdfdag",
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    ) -> None:
        """Evaluate several policies on the same scenes, spawns and seeds."""
        from navi_learner.evaluate import evaluate

        dev = pick_device(device)
        rows = []
        for spec in policies:
            environment = build_env(env, corpus, actors, dev, seed)
            chosen = eval_policy(spec, dev, seed, True, environment)
            rows.append(evaluate(environment, chosen, steps, seed, progress=True))
        print_metrics(rows, as_json)

    @models.command(name="list")
    def models_list(
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    ) -> None:
        """List registered versions and aliases."""
        from navi_learner.registry import ModelRegistry

        reg = ModelRegistry(MODELS_DIR)
        entries, aliases = reg.list(), reg.aliases()
        if as_json:
            typer.echo(json.dumps({"versions": [asdict(e) for e in entries], "aliases": aliases}))
            return
        by_version: dict[str, list[str]] = {}
        for alias, version in aliases.items():
            by_version.setdefault(version, []).append(alias)
        for e in entries:
            tags = ",".join(e.tags)
            typer.echo(
                f"{e.version}  step {e.step_id:>12,}  reward_ema {e.reward_ema:+.4f}  {e.temporal_core:8} "
                f"{e.training_source:3} [{tags}] {' '.join(by_version.get(e.version, []))}  {e.notes}"
            )

    @models.command(name="promote")
    def models_promote(
        checkpoint: Annotated[str, typer.Argument(help="Checkpoint file or an existing version.")],
        alias: Annotated[
            str, typer.Option("--alias", help="Alias to move (latest follows the best).")
        ] = "latest",
        notes: Annotated[str, typer.Option("--notes", help="Free text stored with the version.")] = "",
        tags: Annotated[str, typer.Option("--tags", help="Comma-separated tags.")] = "",
    ) -> None:
        """Copy a checkpoint into the registry as a new immutable version and move an alias."""
        from navi_learner.registry import ModelRegistry, RegistryError

        try:
            entry = ModelRegistry(MODELS_DIR).promote(
                checkpoint, alias, notes, [t for t in tags.split(",") if t]
            )
        except RegistryError as err:
            raise fail(str(err)) from err
        typer.echo(json.dumps(asdict(entry)))

    @models.command(name="rollback")
    def models_rollback(alias: Annotated[str, typer.Argument(help="Alias to move back.")] = "latest") -> None:
        """Point an alias back at its previous version."""
        from navi_learner.registry import ModelRegistry, RegistryError

        try:
            entry = ModelRegistry(MODELS_DIR).rollback(alias)
        except RegistryError as err:
            raise fail(str(err)) from err
        typer.echo(json.dumps(asdict(entry)))

    app.add_typer(models, name="models", rich_help_panel=PANEL)

    @app.command(rich_help_panel=PANEL)
    def export(
        checkpoint: Annotated[Path, typer.Argument(help="Checkpoint to export.")],
        onnx: Annotated[Path, typer.Option("--onnx", help="Output .onnx file.")],
    ) -> None:
        """Export the step-mode policy (obs + recurrent state in; action, value, state out) to ONNX."""
        from navi_learner.checkpoint import CheckpointError
        from navi_learner.export import ExportUnavailable, export_onnx

        try:
            typer.echo(str(export_onnx(checkpoint, onnx)))
        except (ExportUnavailable, CheckpointError) as err:
            raise fail(str(err)) from err

    @app.command(name="run", rich_help_panel=PANEL)
    def run_cmd(
        corpus: Annotated[
            Path, typer.Option("--corpus", help="Training corpus (procedural seed 0, built when missing).")
        ] = DEFAULT_CORPUS,
        unseen: Annotated[
            Path,
            typer.Option(
                "--unseen", help="Unseen corpus for evaluation (procedural seed 1000, built when missing)."
            ),
        ] = UNSEEN_CORPUS,
        budget: Annotated[
            float,
            typer.Option(
                "--budget-s", min=1.0, help="CUDA: training seconds at most (stops earlier at competence)."
            ),
        ] = 600.0,
        eval_every: Annotated[
            float,
            typer.Option(
                "--eval-every-s", min=1.0, help="CUDA: training seconds between unseen evaluations."
            ),
        ] = 30.0,
        cpu_steps: Annotated[
            int,
            typer.Option(
                "--cpu-steps", min=0, help="CPU: env steps of fine-tuning the reference checkpoint."
            ),
        ] = 2048,
        device: DeviceOpt = "auto",
        seed: SeedOpt = 0,
    ) -> None:
        """The main job: build the corpora, train (CUDA: until competent on unseen scenes or the budget; CPU:
        fine-tune the shipped reference checkpoint), promote, evaluate against random and reactive on unseen scenes."""
        from navi_learner.main_job import MainJobConfig, MainJobError, main_job

        dev = pick_device(device)
        job = MainJobConfig(corpus, unseen, MODELS_DIR, dev, seed, budget, eval_every, cpu_steps)
        try:
            report = main_job(job)
        except MainJobError as err:
            raise fail(str(err)) from err
        typer.echo(f"report: {report}")

    @bench.command(name="learn")
    def bench_learn_cmd(
        seeds: Annotated[
            int, typer.Option("--seeds", min=1, help="Training seeds per core (FIRST, FIRST+1, ...).")
        ] = 3,
        first_seed: Annotated[
            int,
            typer.Option(
                "--first-seed", min=0, help="First training seed (spread one study over several jobs)."
            ),
        ] = 0,
        temporal_core: Annotated[
            str, typer.Option("--temporal-core", help="Comma-separated cores to compare: mamba2,gru,mambapy.")
        ] = "mamba2",
        budget: Annotated[
            float,
            typer.Option("--budget-s", min=1.0, help="Training seconds per run (evaluations excluded)."),
        ] = 600.0,
        eval_every: Annotated[
            float,
            typer.Option("--eval-every-s", min=1.0, help="Training seconds between unseen evaluations."),
        ] = 30.0,
        full_budget: Annotated[
            bool,
            typer.Option("--full-budget", help="Keep training after competence (whole learning curves)."),
        ] = False,
        actors: Annotated[
            int, typer.Option("--actors", help="Actors per run (0: 2,048 on CUDA, 8 on CPU).")
        ] = 0,
        rollout_length: Annotated[
            int, typer.Option("--rollout-length", help="Steps per rollout (0: 64 on CUDA, 32 on CPU).")
        ] = 0,
        ppo_epochs: Annotated[int, typer.Option("--ppo-epochs", min=1, help="PPO epochs per rollout.")] = 2,
        lr: Annotated[float, typer.Option("--lr", help="Learning rate.")] = 3e-4,
        max_minibatch: Annotated[
            int,
            typer.Option(
                "--max-minibatch",
                min=256,
                help="Most samples per PPO minibatch (GPU memory; lower it for --parallel).",
            ),
        ] = 16_384,
        eval_actors: Annotated[
            int, typer.Option("--eval-actors", help="Actors per evaluation (0: protocol default).")
        ] = 0,
        eval_steps: Annotated[
            int, typer.Option("--eval-steps", help="Steps per evaluation (0: protocol default).")
        ] = 0,
        episode_steps: Annotated[
            int,
            typer.Option("--eval-episode-steps", help="Episode length in evaluations (0: protocol default)."),
        ] = 0,
        parallel: Annotated[
            int,
            typer.Option("--parallel", min=1, help="Runs at once, sharing the device (wall times overlap)."),
        ] = 1,
        gpus: Annotated[
            int,
            typer.Option(
                "--gpus",
                min=0,
                help="Spread the runs over this many GPUs (cuda:0..), round-robin; with --parallel equal to it, "
                "each GPU trains one run at a time.",
            ),
        ] = 0,
        resolution: Annotated[
            int, typer.Option("--resolution", help="Cells per cube edge of every scene.")
        ] = 512,
        corpus_root: Annotated[
            Path,
            typer.Option("--corpus-root", help="Where the split corpora are built (reused when present)."),
        ] = Path("artifacts/corpus/bench-learn"),
        openarena: Annotated[
            Path,
            typer.Option("--openarena", help="openarena-081-maps pak1-maps.pk3 (left out when missing)."),
        ] = Path("artifacts/data/openarena/pak1-maps.pk3"),
        out: Annotated[
            Path | None, typer.Option("--out", help="Result folder (default artifacts/bench/learn/<time>).")
        ] = None,
        compile_encoder: Annotated[
            bool, typer.Option("--compile/--no-compile", help="torch.compile the encoder on CUDA.")
        ] = True,
        reward: Annotated[
            list[str] | None,
            typer.Option(
                "--reward",
                help="KEY=NUMBER: replace a RewardConfig weight in every env of the job (repeatable), "
                "e.g. --reward exploration_weight=0.2.",
            ),
        ] = None,
        obstacles: ObstaclesOpt = 0,
        squad: SquadOpt = 0,
        procedural_share: Annotated[
            float,
            typer.Option(
                "--procedural-share",
                min=0.0,
                max=0.95,
                help="Repeat the procedural train scenes until about this share of the train corpus is "
                "procedural (0: as built, 16 procedural + 40 OpenArena).",
            ),
        ] = 0.0,
        device: DeviceOpt = "auto",
        as_json: Annotated[
            bool, typer.Option("--json", help="Print the summary as one JSON object.")
        ] = False,
    ) -> None:
        """Train from scratch on a train split, evaluate on unseen scenes during training; time to competence
        (half the reactive baseline's collisions, 1.5x its coverage), learning curves (JSON + PNG)."""
        import time
        from dataclasses import replace

        import torch

        from navi_learner.bench_learn import LearnConfig, bench_learn
        from navi_learner.competence import EvalProtocol
        from navi_learner.envs import parse_reward_overrides
        from navi_learner.evaluate import jsonable

        try:
            overrides = parse_reward_overrides(reward or [])
        except ValueError as err:
            raise fail(str(err)) from err

        dev = pick_device(device)
        cores = tuple(c.strip() for c in temporal_core.split(",") if c.strip())
        protocol = EvalProtocol.for_device(torch.device(dev))
        protocol = replace(
            protocol,
            actors=eval_actors or protocol.actors,
            steps=eval_steps or protocol.steps,
            episode_steps=episode_steps or protocol.episode_steps,
        )
        cfg = LearnConfig(
            seeds=tuple(range(first_seed, first_seed + seeds)),
            temporal_cores=cores,
            time_budget_s=budget,
            eval_every_s=eval_every,
            stop_at_competence=not full_budget,
            actors=actors,
            rollout_length=rollout_length,
            ppo_epochs=ppo_epochs,
            lr=lr,
            max_minibatch=max_minibatch,
            compile=compile_encoder,
            parallel=parallel,
            gpus=gpus,
            protocol=protocol,
            reward=tuple(overrides.items()),
            obstacles=obstacles,
            squad=squad,
            procedural_share=procedural_share,
        )
        folder = out or Path("artifacts/bench/learn") / time.strftime("%Y%m%d-%H%M%S")
        try:
            result = bench_learn(
                cfg, folder, dev, resolution, corpus_root, openarena, say=lambda m: typer.echo(m, err=True)
            )
        except ValueError as err:
            raise fail(str(err)) from err
        if as_json:
            typer.echo(json.dumps(jsonable({"out": str(folder), "summary": result["summary"]})))
        else:
            typer.echo((folder / "report.md").read_text())
            typer.echo(f"results: {folder}")

    @bench.command(name="train")
    def bench_train_cmd(
        actors: Annotated[int, typer.Option("--actors", help="Parallel actors (0: device default).")] = 0,
        temporal_core: CoreOpt = "mamba2",
        device: DeviceOpt = "auto",
        corpus: CorpusOpt = None,
        env: EnvOpt = "sdfdag",
        updates: Annotated[
            int, typer.Option("--updates", help="Measured PPO updates (after 2 warm-up).")
        ] = 5,
        rollout_length: Annotated[
            int, typer.Option("--rollout-length", help="Steps per rollout (0: default).")
        ] = 0,
        compile_encoder: Annotated[
            bool, typer.Option("--compile/--no-compile", help="torch.compile the encoder on CUDA.")
        ] = True,
        obs_storage: ObsStorageOpt = "auto",
        max_minibatch: MaxMinibatchOpt = 8_192,
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
        nproc: Annotated[
            int,
            typer.Option(
                "--nproc",
                min=1,
                help="Also measure N data-parallel ranks (torchrun, one per GPU, --actors each) after one "
                "process: per-rank and total SPS, scaling efficiency SPS(N) / (N x SPS(1)).",
            ),
        ] = 1,
        result_file: Annotated[
            Path | None, typer.Option("--result-file", hidden=True, help="Write the JSON here instead.")
        ] = None,
    ) -> None:
        """Env only / env + inference / env + training SPS and ms per stage."""
        from dataclasses import replace

        import torch

        from navi_learner import dist
        from navi_learner.bench import bench_train, bench_train_scaling
        from navi_learner.config import StorageError, default_actors

        if nproc > 1 and not dist.launched():
            args = dist.strip_option(dist.strip_option(sys.argv[1:], "--nproc"), "--result-file")
            try:
                result = bench_train_scaling(nproc, args)
            except RuntimeError as err:
                raise fail(str(err)) from err
        else:
            try:
                d, dev = dist.setup(pick_device(device))
            except ValueError as err:
                raise fail(str(err)) from err
            try:
                cfg = train_config(
                    actors, temporal_core, rollout_length, 1, 5e-4, 0, 10**12, dev, 0, obs_storage,
                    max_minibatch, compile_encoder,
                )  # fmt: skip
                n = actors or default_actors(torch.device(dev))
                environment = build_env(env, corpus, n, dev, d.rank, d.rank, d.world)
                result = bench_train(environment, replace(cfg, n_actors=n), updates=updates, dist=d)
            except (dist.DistError, StorageError) as err:
                raise fail(str(err)) from err
            finally:
                dist.shutdown(d)
            if result_file is not None:
                if d.main:
                    result_file.write_text(json.dumps(result))
                dist.leave(d)
                return
        typer.echo(json.dumps(result) if as_json else "\n".join(f"{k}: {v}" for k, v in result.items()))
        sys.stdout.flush()
