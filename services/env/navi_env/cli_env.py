"""`navi qualify`, `navi corpus build|list` and `navi bench env` (registered through navi_env.cli)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

PANEL = "Environment"


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def _say(line: str) -> None:
    if sys.stderr.isatty():
        typer.echo(line, err=True)


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add the environment's commands to the root app and the `bench` group."""
    corpus_app = typer.Typer(
        help="Training corpora: folders of qualified .gmdag scenes.", no_args_is_help=True
    )

    @app.command("qualify", rich_help_panel=PANEL)
    def qualify(
        file: Annotated[Path, typer.Argument(help="The .gmdag scene to judge.")],
        json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")] = False,
        device: Annotated[str, typer.Option(help="Device that traces the probe rays (cpu, cuda).")] = "cpu",
    ) -> None:
        """Probe a 5x7x5 grid of spawn candidates with 48x12 rays; exit 1 when the scene fails."""
        from navi_compiler.gmdag import GmdagError
        from navi_env.qualify import qualify_scene
        from navi_env.scene import load_scene

        if not file.is_file():
            raise _fail(f"file not found: {file}")
        try:
            corpus = load_scene(file, device)
        except (GmdagError, OSError, RuntimeError, ValueError) as exc:
            raise _fail(f"{file}: {exc}") from exc
        result = qualify_scene(corpus, 0)
        if json_out:
            typer.echo(json.dumps({"file": str(file), **result.to_json()}))
        else:
            typer.echo(f"{file}: {result.verdict.upper()} - {result.reason}")
            typer.echo(
                f"  viable spawns {result.viable_spawns} / {result.candidates} candidates "
                f"({result.free_candidates} free), best starvation {result.best_starvation:.3f}"
            )
        if not result.passed:
            raise typer.Exit(1)

    @corpus_app.command("build")
    def corpus_build(
        out: Annotated[Path, typer.Option("--out", "-o", help="Corpus folder to create or replace.")],
        src_dir: Annotated[
            Path | None, typer.Argument(help="Folder of scene sources (meshes, .bsp, .pk3, .gmdag).")
        ] = None,
        default: Annotated[
            bool, typer.Option("--default", help="Build the procedural default corpus.")
        ] = False,
        resolution: Annotated[
            int, typer.Option(help="Cells per cube edge of every compiled scene.", min=8)
        ] = 512,
        count: Annotated[int, typer.Option(help="Procedural scenes to generate with --default.", min=1)] = 16,
        seed: Annotated[int, typer.Option(help="Seed of the procedural scenes with --default.")] = 0,
        device: Annotated[str, typer.Option(help="Device that traces the qualification rays.")] = "cpu",
        json_out: Annotated[bool, typer.Option("--json", help="Print the manifest summary as JSON.")] = False,
    ) -> None:
        """Compile, check and qualify every source into OUT; the old corpus is replaced only on success."""
        from navi_env.corpus import CorpusError, build_corpus, build_default_corpus, find_sources

        if default == (src_dir is not None):
            raise _fail("give either SRC_DIR or --default")
        try:
            if src_dir is None:
                manifest = build_default_corpus(out, resolution, count, seed, device, progress=_say)
            else:
                sources = find_sources(src_dir)
                if not sources:
                    raise _fail(f"no scene sources found in {src_dir}")
                manifest = build_corpus(sources, out, resolution, device, progress=_say)
        except CorpusError as exc:
            raise _fail(f"{exc} (the previous corpus at {out} is unchanged)") from exc
        summary = {"corpus": str(out), **manifest.summary()}
        if json_out:
            typer.echo(json.dumps(summary))
        else:
            typer.echo(f"{out}: {len(manifest.scenes)} scenes, {len(manifest.rejected)} rejected")

    @corpus_app.command("list")
    def corpus_list(
        corpus: Annotated[Path, typer.Argument(help="Corpus folder.")],
        json_out: Annotated[bool, typer.Option("--json", help="Print the manifest as JSON.")] = False,
    ) -> None:
        """List a corpus's scenes with their size and qualification."""
        from navi_env.corpus import CorpusError, read_manifest

        try:
            manifest = read_manifest(corpus)
        except CorpusError as exc:
            raise _fail(str(exc)) from exc
        if json_out:
            typer.echo(json.dumps(manifest.to_json()))
            return
        typer.echo(f"{corpus}: {len(manifest.scenes)} scenes (built {manifest.created_at})")
        for s in manifest.scenes:
            q = s.qualification
            typer.echo(
                f"  {s.name:<28} {s.resolution:>5}^3  {s.voxel_size:8.4f} m  {s.bytes / 1e6:8.2f} MB  "
                f"spawns {q.get('viable_spawns')}  best starvation {q.get('best_starvation')}"
                + (f"  obstacles {s.obstacles}" if s.obstacles else "")
            )
        for r in manifest.rejected:
            typer.echo(f"  rejected {r['source']}: {r['reason']}")

    app.add_typer(corpus_app, name="corpus", rich_help_panel=PANEL)

    @bench.command("env")
    def bench_env(
        gmdag: Annotated[Path | None, typer.Option(help="One .gmdag scene.")] = None,
        corpus: Annotated[Path | None, typer.Option(help="A corpus folder.")] = None,
        actors: Annotated[int, typer.Option(help="Actors stepped together.", min=1)] = 4,
        steps: Annotated[int, typer.Option(help="Timed steps (after 5 warm-up steps).", min=1)] = 50,
        device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
        azimuth: Annotated[int, typer.Option(help="Azimuth bins.")] = 256,
        elevation: Annotated[int, typer.Option(help="Elevation bins.")] = 48,
        seed: Annotated[int, typer.Option(help="Seed of the environment and the random actions.")] = 0,
        threads: Annotated[
            int, typer.Option(help="CPU threads for torch and the CPU tracer (0: torch's default).", min=0)
        ] = 0,
        obstacles: Annotated[
            int,
            typer.Option(
                "--obstacles",
                min=0,
                max=64,
                help="K scripted moving obstacles per actor (EnvConfig.obstacles; traced, felt by physics).",
            ),
        ] = 0,
        squad: Annotated[
            int,
            typer.Option(
                "--squad", min=0, max=64, help="Squads of this many actors see and collide with each other."
            ),
        ] = 0,
        json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")] = False,
    ) -> None:
        """Env-steps per second of SdfDagEnv with random actions, and milliseconds per stage."""
        if threads:
            import torch

            torch.set_num_threads(threads)
        if (gmdag is None) == (corpus is None):
            raise _fail("give exactly one of --gmdag FILE or --corpus DIR")
        try:
            result = run_bench(
                gmdag, corpus, actors, steps, device, azimuth, elevation, seed, obstacles, squad
            )
        except (OSError, RuntimeError, ValueError) as exc:
            raise _fail(str(exc)) from exc
        if json_out:
            typer.echo(json.dumps(result))
        else:
            for key, value in result.items():
                typer.echo(f"{key:>22}: {value}")


def run_bench(
    gmdag: Path | None,
    corpus: Path | None,
    actors: int,
    steps: int,
    device: str,
    azimuth: int,
    elevation: int,
    seed: int,
    obstacles: int = 0,
    squad: int = 0,
) -> dict[str, object]:
    """Step SdfDagEnv `steps` times with uniform random actions; returns the bench JSON object. With
    `obstacles` K > 0 every actor has K scripted moving obstacles (their collisions and the share of rays
    that hit them are reported)."""
    import time

    import torch

    from navi_env.config import EnvConfig, ObstacleConfig
    from navi_env.corpus import load_corpus
    from navi_env.env import SdfDagEnv, StageTimer
    from navi_env.scene import load_scene

    spawns: list[torch.Tensor] | None = None
    if corpus is not None:
        scenes, manifest = load_corpus(corpus, device)
        spawns = manifest.spawn_tensors()
    elif gmdag is not None:
        scenes = load_scene(gmdag, device)
    else:
        raise ValueError("give a .gmdag file or a corpus folder")
    config = EnvConfig(
        azimuth_bins=azimuth, elevation_bins=elevation, obstacles=ObstacleConfig(count=obstacles, squad=squad)
    )
    env = SdfDagEnv(scenes, actors, device, config, spawns, seed)
    g = torch.Generator(device=env.device).manual_seed(seed)
    env.reset(seed=seed)
    actions = torch.empty(actors, 4, device=env.device)  # (N, 4)
    for _ in range(5):
        env.step(actions.uniform_(-1.0, 1.0, generator=g))
    sync = torch.cuda.synchronize if env.device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(actions.uniform_(-1.0, 1.0, generator=g))
    sync()
    seconds = time.perf_counter() - t0
    env.timer = StageTimer(env.device)  # a second, timed pass for the per-stage split
    hit_obstacle = torch.zeros((), device=env.device)  # () rays that hit an obstacle, summed over steps
    struck = torch.zeros((), device=env.device)  # () collisions with obstacles
    bumped = torch.zeros((), device=env.device)  # () collisions between drones
    for _ in range(steps):
        out = env.step(actions.uniform_(-1.0, 1.0, generator=g))
        hit_obstacle += (env.semantic == config.obstacles.semantic_class + 1).sum()
        struck += out.info["obstacle_collision"].sum()
        bumped += out.info["drone_collision"].sum()
    per_stage = {k: round(v / steps, 4) for k, v in env.timer.totals_ms().items()}
    extra: dict[str, object] = {}
    if squad >= 2:
        extra["squad"] = squad
        extra["drone_collisions_per_1k"] = round(1000.0 * float(bumped) / (steps * actors), 3)
    if obstacles:
        extra |= {
            "obstacle_hit_fraction": round(float(hit_obstacle) / (steps * actors * config.rays), 5),
            "obstacle_collisions_per_1k": round(1000.0 * float(struck) / (steps * actors), 3),
        }
    return {
        "device": str(env.device),
        "actors": actors,
        "steps": steps,
        "scenes": len(scenes),
        "steps_per_s": round(actors * steps / seconds, 1),
        "ms_per_step": round(1000.0 * seconds / steps, 4),
        "ms_per_stage": per_stage,
        "bytes_per_actor": env.bytes_per_actor(),
        "obs_shape": [actors, *env.obs_shape],
        "threads": torch.get_num_threads(),
        "obstacles_per_actor": obstacles,
        **extra,
    }
