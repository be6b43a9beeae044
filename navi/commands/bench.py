"""`navi bench compile|trace|env|wrappers|freespace|openfloor|train|learn|transfer|trainers`: each measures
one stage (or learning itself) and prints its result; `--json` prints one JSON object and `--record DIR`
appends it to DIR/DATE-GPU.jsonl (docs/PERFORMANCE.md). Targets are benchmarks, never timed tests."""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, Any

import typer

from navi.commands.common import (
    CorpusOpt,
    EnvOpt,
    RecordOpt,
    fail,
    pick_device,
    record_result,
)
from navi.commands.compiler import (
    EngineChoice,
    check_engine_device,
    compile_or_fail,
    compile_summary,
    load_source,
    max_source_bytes,
)
from navi.commands.learner import COMMAND_DEVICE, EngineOpt, ObstaclesOpt, SquadOpt, build_env, train_config
from navi.commands.options import Settings, config_options
from navi_env.config import EnvConfig
from navi_env.corpus.openarena import DEFAULT_PK3
from navi_learner.config import TrainConfig, learning_recipe

GmdagOpt = Annotated[Path | None, typer.Option(help="One .gmdag scene.")]
SceneCorpusOpt = Annotated[Path | None, typer.Option(help="A corpus folder.")]
EnvActorsOpt = Annotated[int, typer.Option(help="Actors stepped together.", min=1)]
EnvDeviceOpt = Annotated[str, typer.Option(help="cpu or cuda.")]
AzimuthOpt = Annotated[int, typer.Option(help="Azimuth bins.")]
ElevationOpt = Annotated[int, typer.Option(help="Elevation bins.")]
EnvSeedOpt = Annotated[int, typer.Option(help="Seed of the environment and the random actions.")]
ThreadsOpt = Annotated[
    int, typer.Option(help="CPU threads for torch and the CPU tracer (0: torch's default).", min=0)
]
JsonOutOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")]
ResolutionOpt = Annotated[int, typer.Option("--resolution", help="Cells per cube edge of every scene.")]
OpenArenaOpt = Annotated[
    Path, typer.Option("--openarena", help="openarena-081-maps pak1-maps.pk3 (left out when missing).")
]

app = typer.Typer(
    help="Benchmarks; each prints its result (--json: one JSON object; --record DIR: appended to "
    "DIR/DATE-GPU.jsonl, docs/PERFORMANCE.md).",
    no_args_is_help=True,
)


@app.command("compile")
def bench_compile(
    src: Annotated[str, typer.Argument(help="Scene source (as for `navi compile`).")],
    resolution: Annotated[int, typer.Option(help="Cells per cube edge.")] = 512,
    map_name: Annotated[str | None, typer.Option("--map", help="Map name inside a .pk3.")] = None,
    scale: Annotated[float | None, typer.Option(help="Meters per source unit.")] = None,
    engine: Annotated[EngineChoice, typer.Option(help="cpp, ref or torch.")] = EngineChoice.cpp,
    threads: Annotated[int, typer.Option(help="C++ worker threads (0: all cores).", min=0)] = 0,
    device: Annotated[str, typer.Option(help="Torch device for --engine torch (cpu, cuda).")] = "cpu",
    json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object (always on).")] = True,
    record: RecordOpt = None,
) -> None:
    """Time one compile (nothing written) and print the stats as one JSON object. With --engine
    torch a first (warm-up) compile runs before the timed one; its time is `warmup_seconds`."""
    import os

    check_engine_device(engine, device)
    t0 = time.perf_counter()
    scene = load_source(src, map_name, scale, False, None, max_source_bytes(None))
    load_seconds = time.perf_counter() - t0
    warmup: float | None = None
    if engine == EngineChoice.torch:
        t1 = time.perf_counter()
        compile_or_fail(scene, resolution, engine="torch", device=device)
        warmup = time.perf_counter() - t1
    _, stats = compile_or_fail(scene, resolution, engine=engine.value, threads=threads, device=device)
    result = compile_summary(asdict(stats), None, load_seconds)
    result.update(
        {
            "source": src,
            "map": map_name,
            "cpu_count": os.cpu_count(),
            "json": json_out,
            "device": device if engine == EngineChoice.torch else "cpu",
            "warmup_seconds": warmup,
        }
    )
    typer.echo(json.dumps(result))
    if record is not None:
        record_result(result, "compile", device, record)


@app.command("trace", rich_help_panel="Tracer")
def bench_trace_cmd(
    gmdag: Annotated[Path | None, typer.Option("--gmdag", help="Scene file (.gmdag).")] = None,
    corpus_dir: Annotated[
        Path | None,
        typer.Option(
            "--corpus",
            help="Instead of --gmdag: measure every .gmdag of this folder, one at a time, and summarise "
            "(min / median / max rate, steps and bytes; maps below 10 G rays/s and below 100x dense).",
        ),
    ] = None,
    agents: Annotated[int, typer.Option(help="Agents (batch), each casting the full pattern.")] = 4096,
    device: Annotated[str, typer.Option(help="cpu, cuda or cuda:N.")] = "cuda",
    steps: Annotated[int, typer.Option("--steps", help="Timed launches (after warm-up).")] = 20,
    azimuth: Annotated[int, typer.Option(help="Azimuth bins of the spherical pattern.")] = 256,
    elevation: Annotated[int, typer.Option(help="Elevation bins of the spherical pattern.")] = 48,
    max_steps: Annotated[int, typer.Option(help="Sphere-tracing steps per ray.")] = 256,
    hit_slope: Annotated[
        float,
        typer.Option(
            help="Growth of the hit threshold with distance, 0.1 voxel + slope * t; the default is "
            "the env's (EnvConfig.hit_slope), 0 a fixed threshold.",
        ),
    ] = EnvConfig.hit_slope,
    vs_warp: Annotated[
        bool, typer.Option("--vs-warp", help="Also cast the same rays with a Warp mesh BVH.")
    ] = False,
    mesh: Annotated[
        Path | None,
        typer.Option(help="Source mesh for --vs-warp: .npz with vertices (V,3), triangles (F,3)."),
    ] = None,
    vs_nanovdb: Annotated[
        bool,
        typer.Option(
            "--vs-nanovdb",
            help="Also trace the same rays through a NanoVDB narrow band of the scene's own samples "
            "(Warp Volume, float32, trilinear, the same step and hit rules); with --corpus, on every map.",
        ),
    ] = False,
    nanovdb_bands: Annotated[
        str,
        typer.Option(
            "--nanovdb-bands", help="Narrow-band half widths in voxels for --vs-nanovdb, comma-separated."
        ),
    ] = "3,8,24",
    nanovdb_scales: Annotated[
        str,
        typer.Option(
            "--nanovdb-scales",
            help="Voxel sizes of the band for --vs-nanovdb, comma-separated, as multiples of the scene's "
            "own cell (2: the same field sampled on a lattice twice as coarse).",
        ),
    ] = "1",
    nanovdb_sampling: Annotated[
        str,
        typer.Option(
            "--nanovdb-sampling",
            help="Marches for --vs-nanovdb, comma-separated: linear (a trilinear sample every step) and "
            "closest-far (the nearest sample alone while it bounds the distance above 2 voxels).",
        ),
    ] = "linear",
    obstacles: Annotated[
        int,
        typer.Option(
            "--obstacles",
            min=0,
            help="Dynamic primitives per agent (spheres, capsules, boxes, oriented boxes 1-8 m away), "
            "moved before every launch and traced in the same pass.",
        ),
    ] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    record: RecordOpt = None,
) -> None:
    """G rays/s and observations/s of the tracer with the 256x48 spherical pattern."""
    from navi_bench.nanovdb import SAMPLINGS
    from navi_bench.trace import TraceBenchConfig, bench_trace, bench_trace_maps
    from navi_compiler.gmdag import GmdagError
    from navi_env.tracer.scene import load_scene

    if agents < 1 or steps < 1:
        raise fail("--agents and --steps must be at least 1")
    if not 0.0 <= hit_slope < 1.0:
        raise fail(f"--hit-slope must be in [0, 1), got {hit_slope}")
    if (gmdag is None) == (corpus_dir is None):
        raise fail("give one of --gmdag FILE or --corpus DIR")
    if vs_warp and mesh is None:
        raise fail("--vs-warp needs --mesh FILE.npz (vertices, triangles) of the scene's source mesh")
    try:
        bands = tuple(float(b) for b in nanovdb_bands.split(",") if b.strip())
    except ValueError:
        raise fail(f"--nanovdb-bands expects numbers separated by commas, got {nanovdb_bands!r}") from None
    if vs_nanovdb and (not bands or min(bands) <= 0):
        raise fail("--nanovdb-bands needs at least one band, every one above 0 voxels")
    try:
        scales = tuple(int(k) for k in nanovdb_scales.split(",") if k.strip())
    except ValueError:
        raise fail(
            f"--nanovdb-scales expects whole numbers separated by commas, got {nanovdb_scales!r}"
        ) from None
    if vs_nanovdb and (not scales or min(scales) < 1):
        raise fail("--nanovdb-scales needs at least one voxel scale, every one 1 or more")
    samplings = tuple(x.strip() for x in nanovdb_sampling.split(",") if x.strip())
    known = tuple(SAMPLINGS)
    if vs_nanovdb and (not samplings or any(x not in known for x in samplings)):
        raise fail(
            f"--nanovdb-sampling takes {' or '.join(known)}, comma-separated; got {nanovdb_sampling!r}"
        )
    if vs_nanovdb and obstacles:
        raise fail("--vs-nanovdb traces the static scene: leave out --obstacles")
    cfg = TraceBenchConfig(
        agents=agents, device=device, launches=steps, azimuth_bins=azimuth, elevation_bins=elevation,
        max_steps=max_steps, obstacles=obstacles, hit_slope=hit_slope,
    )  # fmt: skip
    nanovdb = nanovdb_anchor(cfg, bands, scales, samplings) if vs_nanovdb else None
    if corpus_dir is not None:
        if vs_warp:
            raise fail("--vs-warp needs one scene (--gmdag)")
        paths = sorted(corpus_dir.glob("*.gmdag")) if corpus_dir.is_dir() else []
        if not paths:
            raise fail(f"{corpus_dir} holds no .gmdag files")
        try:
            report = bench_trace_maps(paths, cfg, lambda line: typer.echo(line, err=True), nanovdb)
        except (OSError, GmdagError, ValueError, RuntimeError) as exc:
            raise fail(str(exc)) from None
        if record is not None:
            record_result(report, "trace", device, record)
        if as_json:
            sys.stdout.write(json.dumps(report) + "\n")
        else:
            for key, value in report["summary"].items():  # type: ignore[attr-defined]
                typer.echo(f"{key:>26}: {value}")
        return
    assert gmdag is not None
    try:
        corpus = load_scene(gmdag, device)
        measured = bench_trace(corpus, cfg)
        result: dict[str, object] = dataclasses.asdict(measured)
        if vs_warp and mesh is not None:
            from navi_bench.warp import WarpUnavailable, bench_warp

            try:
                result["warp"] = bench_warp(corpus, cfg, mesh, measured.ms_per_launch)
            except WarpUnavailable as exc:
                result["warp"] = {"error": str(exc)}
                typer.echo(f"--vs-warp skipped: {exc}", err=True)
        if nanovdb is not None:
            result |= nanovdb(corpus, measured)
    except (OSError, GmdagError, ValueError, RuntimeError) as exc:
        raise fail(str(exc)) from None
    if record is not None:
        record_result(result, "trace", device, record)
    if as_json:
        sys.stdout.write(json.dumps(result) + "\n")
        return
    for key, value in result.items():
        typer.echo(f"{key:>20}: {value}")


def nanovdb_anchor(
    cfg: Any,
    bands: tuple[float, ...],
    scales: tuple[int, ...] = (1,),
    samplings: tuple[str, ...] = ("linear",),
) -> Callable[[Any, Any], dict[str, object]]:
    """`--vs-nanovdb`: for a scene and the tracer's result on it, {"nanovdb": one dict per voxel scale,
    band and sampling}, or {"nanovdb": {"error": why}} where warp-lang is missing (also said on stderr)."""

    def measure(corpus: Any, measured: Any) -> dict[str, object]:
        from navi_bench.nanovdb import NanoVDBUnavailable, bench_nanovdb

        try:
            return {"nanovdb": bench_nanovdb(corpus, cfg, measured.ms_per_launch, bands, scales, samplings)}
        except NanoVDBUnavailable as exc:
            typer.echo(f"--vs-nanovdb skipped: {exc}", err=True)
            return {"nanovdb": {"error": str(exc)}}

    return measure


def use_scene_options(gmdag: Path | None, corpus: Path | None, threads: int) -> None:
    """Check that exactly one of --gmdag and --corpus is given, and apply --threads."""
    if threads:
        import torch

        torch.set_num_threads(threads)
    if (gmdag is None) == (corpus is None):
        raise fail("give exactly one of --gmdag FILE or --corpus DIR")


@app.command("env")
def bench_env_cmd(
    gmdag: GmdagOpt = None,
    corpus: SceneCorpusOpt = None,
    actors: EnvActorsOpt = 4,
    steps: Annotated[int, typer.Option(help="Timed steps (after 5 warm-up steps).", min=1)] = 50,
    device: EnvDeviceOpt = "cpu",
    azimuth: AzimuthOpt = 256,
    elevation: ElevationOpt = 48,
    seed: EnvSeedOpt = 0,
    threads: ThreadsOpt = 0,
    obstacles: ObstaclesOpt = 0,
    squad: SquadOpt = 0,
    json_out: JsonOutOpt = False,
    record: RecordOpt = None,
) -> None:
    """Env-steps per second of SdfDagEnv with random actions, and milliseconds per stage."""
    from navi_bench.env import bench_env

    use_scene_options(gmdag, corpus, threads)
    try:
        result = bench_env(gmdag, corpus, actors, steps, device, azimuth, elevation, seed, obstacles, squad)
    except (OSError, RuntimeError, ValueError) as exc:
        raise fail(str(exc)) from exc
    if record is not None:
        record_result(result, "env", device, record)
    if json_out:
        typer.echo(json.dumps(result))
    else:
        for key, value in result.items():
            typer.echo(f"{key:>22}: {value}")


@app.command("wrappers")
def bench_wrappers_cmd(
    gmdag: GmdagOpt = None,
    corpus: SceneCorpusOpt = None,
    actors: EnvActorsOpt = 4,
    steps: Annotated[int, typer.Option(help="Timed steps per round.", min=1)] = 50,
    repeats: Annotated[int, typer.Option(help="Rounds; each variant reports its best.", min=1)] = 3,
    device: EnvDeviceOpt = "cpu",
    azimuth: AzimuthOpt = 256,
    elevation: ElevationOpt = 48,
    seed: EnvSeedOpt = 0,
    threads: ThreadsOpt = 0,
    json_out: JsonOutOpt = False,
    record: RecordOpt = None,
) -> None:
    """Env-steps per second of the raw env, the Gymnasium, skrl and TorchRL adapters, in one job."""
    from navi_bench.ecosystem import bench_wrappers

    use_scene_options(gmdag, corpus, threads)
    try:
        result = bench_wrappers(gmdag, corpus, actors, steps, device, azimuth, elevation, seed, repeats)
    except (OSError, RuntimeError, ValueError) as exc:
        raise fail(str(exc)) from exc
    if record is not None:
        record_result(result, "wrappers", device, record)
    if json_out:
        typer.echo(json.dumps(result))
    else:
        for key, value in result.items():
            typer.echo(f"{key:>14}: {value}")


def flight_row(m: Any) -> dict[str, float | None]:
    """What `bench freespace --evaluate` reports of one policy on one scene (m: EvalMetrics): collisions and
    coverage, and why the coverage is what it is: meters flown, meters flown per new cell (revisits; a
    hovering drone flies little, a circling one many meters per cell), the view clearance and the reward
    per step (does the reward prefer the policy that covers more?)."""
    per_cell = m.distance_per_1k / m.coverage_per_1k if m.coverage_per_1k > 0 else None
    return {
        "collisions_per_1k": m.collisions_per_1k,
        "coverage_per_1k": m.coverage_per_1k,
        "distance_per_1k": round(m.distance_per_1k, 1),
        "m_per_new_cell": None if per_cell is None else round(per_cell, 2),
        "mean_clearance": round(m.mean_clearance, 3),
        "reward_per_step": round(m.reward_per_step, 4),
    }


@app.command("freespace")
def bench_freespace_cmd(
    corpus: Annotated[Path, typer.Option("--corpus", help="Corpus folder (manifest.json and its scenes).")],
    device: Annotated[str, typer.Option(help="cpu, cuda or cuda:N.")] = "cpu",
    cell: Annotated[float, typer.Option(help="Lattice spacing in meters.", min=0.05)] = 0.5,
    radius: Annotated[
        float | None, typer.Option(help="Clearance a free voxel needs, meters (default: the drone radius).")
    ] = None,
    episode_steps: Annotated[
        int, typer.Option(help="Episode length the coverage bound is for (the evaluation's 500).", min=1)
    ] = 500,
    goals: Annotated[
        int, typer.Option(help="Also build a point-goal table of this many goals per scene, timed.", min=0)
    ] = 0,
    evaluate_actors: Annotated[
        int,
        typer.Option(
            "--evaluate",
            help="Also fly the reactive baseline (and --checkpoint) on each scene alone with this many actors "
            "for two episodes of --episode-steps (env seed 12345), beside the bound and the planner.",
            min=0,
        ),
    ] = 0,
    checkpoint: Annotated[Path | None, typer.Option(help="A checkpoint to evaluate with --evaluate.")] = None,
    reward: Annotated[
        list[str] | None,
        typer.Option(
            "--reward",
            help="KEY=NUMBER: score the planner's flight (and the --evaluate flights) with this RewardConfig "
            "field replaced (repeatable), e.g. --reward proximity_distance=1.0: which flight a reward prefers, "
            "scene by scene.",
        ),
    ] = None,
    json_out: JsonOutOpt = False,
    record: RecordOpt = None,
) -> None:
    """Each scene as free space at the drone's radius: voxels, connected parts, a geodesic field from a
    spawn (times and bytes), the coverage per 1,000 steps its spawns can reach at most (speed limit
    and the spawn's free part), and how open that part is (the view clearance at 64 of its voxels: its
    median and the share at the 10 m cap)."""
    from navi_bench.survey import survey_corpus
    from navi_learner.envs.factory import parse_reward_overrides

    try:
        overrides = parse_reward_overrides(reward or [])
        result = survey_corpus(corpus, device, cell, radius, episode_steps, goals, overrides)
        result["reward"] = overrides
        if evaluate_actors:
            from navi_learner.evaluation.competence import EvalProtocol, per_scene

            protocol = EvalProtocol(evaluate_actors, 2 * episode_steps, episode_steps)  # two episodes each
            flown = per_scene(corpus, len(result["scenes"]), protocol, device, checkpoint, overrides)
            for row, metrics in zip(result["scenes"], flown, strict=True):
                row["evaluated"] = {name: flight_row(m) for name, m in metrics.items()}
    except (OSError, RuntimeError, ValueError) as exc:
        raise fail(str(exc)) from exc
    if record is not None:
        record_result(result, "freespace", device, record)
    if json_out:
        typer.echo(json.dumps(result))
        return
    for row in result["scenes"]:
        typer.echo(
            f"{row['name']:>24}: grid {row['grid']}, free {row['free_share']:.1%}, {row['parts']} parts, "
            f"reachable {row['reachable_cells_median']} cells, coverage <= {row['coverage_bound_per_1k']}/1k, "
            f"planner {row['planner_coverage_per_1k']}/1k at {row['planner_speed_m_s']} m/s "
            f"(reward {row['planner_reward_per_step']}/step), "
            f"view clearance median {row['view_clearance_median_m']} m, {row['open_share']:.0%} open, "
            f"{sum(row['seconds'].values()):.2f} s"
            + "".join(
                f", {k} {v['coverage_per_1k']:.0f}/1k ({v['distance_per_1k']:.0f} m, {v['m_per_new_cell']} m per cell, "
                f"reward {v['reward_per_step']}/step)"
                for k, v in row.get("evaluated", {}).items()
            )
        )


@app.command("openfloor")
def bench_openfloor_cmd(
    checkpoints: Annotated[
        list[Path] | None,
        typer.Argument(help="Explore checkpoints to fly (default: the shipped explore reference)."),
    ] = None,
    device: Annotated[str, typer.Option(help="cpu, cuda or cuda:N.")] = "cpu",
    widths: Annotated[
        str,
        typer.Option(
            "--widths", help="Floor edges in meters, comma-separated (the sky at --sky-ratio of each)."
        ),
    ] = "15,30,60,120",
    sky_ratio: Annotated[
        float, typer.Option("--sky-ratio", min=0.01, help="The sky's height as a share of the floor's width.")
    ] = 1.0 / 3.0,
    steps: Annotated[int, typer.Option("--steps", min=2, help="Steps flown (dt 0.1 s).")] = 300,
    actors: Annotated[int, typer.Option("--actors-per-start", min=1, help="Drones per start height.")] = 8,
    folder: Annotated[
        Path, typer.Option("--scenes", help="Where the floors are built (reused when present).")
    ] = Path("artifacts/corpus/open-floor"),
    json_out: JsonOutOpt = False,
    record: RecordOpt = None,
) -> None:
    """Does a drone hold its height where nothing is near? Flat walled floors under an undrawn sky, nothing
    else; drones start above the centre at 1-16 m and fly 30 s. Per floor: the height they end at and the
    share pressed to the floor, for each checkpoint and the reactive avoider. A drone that sinks in open
    space shows it here in seconds, without the real maps (docs/TRAINING.md, "Real maps never seen")."""
    import torch

    from navi_learner.evaluation.baselines import reactive_for_env
    from navi_learner.evaluation.evaluate import CheckpointPolicy, jsonable
    from navi_learner.evaluation.main_job import REFERENCE
    from navi_learner.evaluation.open_floor import (
        OpenFloorConfig,
        build_open_floors,
        open_floor_env,
        open_floor_probe,
        probe_table,
    )
    from navi_learner.serving.checkpoint import load_checkpoint

    started = time.perf_counter()
    dev = pick_device(device)
    try:
        cfg = OpenFloorConfig(
            widths=tuple(float(w) for w in widths.split(",") if w.strip()),
            sky_ratio=sky_ratio,
            steps=steps,
            actors_per_start=actors,
        )
        say = None if json_out else typer.echo
        env = open_floor_env(build_open_floors(folder, cfg, say), cfg, dev)
        policies: list[Any] = []
        for path in checkpoints or [REFERENCE]:
            task = load_checkpoint(path).meta.config.get("task", "explore")
            if task != "explore":
                raise ValueError(
                    f"{path} was trained for {task}; the open-floor probe flies explore checkpoints"
                )
            policy = CheckpointPolicy(path, torch.device(dev))
            policy.name = str(path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path)
            if policy.obs_shape != env.obs_shape:
                raise ValueError(f"{path} sees {policy.obs_shape}, the probe's view is {env.obs_shape}")
            policies.append(policy)
        policies.append(reactive_for_env(env))
        rows = [row for policy in policies for row in open_floor_probe(policy, env, cfg)]
    except (OSError, RuntimeError, ValueError) as exc:
        raise fail(str(exc)) from exc
    result = {
        "config": dataclasses.asdict(cfg),
        "rows": [dataclasses.asdict(r) for r in rows],
        "seconds": round(time.perf_counter() - started, 1),
    }
    if record is not None:
        record_result(result, "openfloor", device, record)
    if json_out:
        typer.echo(json.dumps(jsonable(result)))
    else:
        typer.echo(probe_table(rows))


LEARN_OPTIONS = (
    "n_actors",
    "rollout_length",
    "ppo_epochs",
    "lr",
    "target_kl",
    "mean_bound_coef",
    "compile_rollout",
    "compile_update",
    "update_graphs",
    "tf32",
    "max_minibatch",
    "compile",
    "device",
    "task",
)
"""The TrainConfig settings `navi bench learn` takes as options, on the learning recipe's defaults."""


@app.command(name="learn")
@config_options(
    learning_recipe(),
    LEARN_OPTIONS,
    defaults=COMMAND_DEVICE,
    helps={
        "n_actors": "Actors per run (0: 8,192 on CUDA, 2,048 on a GPU under 36 GiB, 8 on CPU).",
        "rollout_length": "Steps per rollout (0: 64 on CUDA, 32 on CPU).",
    },
)
def bench_learn_cmd(
    *,
    seeds: Annotated[
        int, typer.Option("--seeds", min=1, help="Training seeds per core (FIRST, FIRST+1, ...).")
    ] = 3,
    first_seed: Annotated[
        int,
        typer.Option("--first-seed", min=0, help="First training seed (spread one study over several jobs)."),
    ] = 0,
    temporal_cores: Annotated[
        str, typer.Option("--temporal-core", help="Comma-separated cores to compare: mamba2,gru,mambapy.")
    ] = "mamba2",
    arms: Annotated[
        list[str] | None,
        typer.Option(
            "--arm",
            help="CORE[/KEY=VALUE[,KEY=VALUE...]]: an arm to compare, a core with EngineConfig fields on top "
            "of --engine, RewardConfig weights on top of --reward, and PPO settings (lr, mean_bound_coef, "
            "ent_coef, clip_coef, vf_coef, gae_lambda, gamma) and run sizes (actors, rollout_length) in "
            "place of the job's, for its training (evaluations fly the job's reward) (repeatable; replaces "
            "--temporal-core), e.g. --arm mamba2 --arm mamba2/attention=fused --arm "
            "mamba2/collision_weight=9 --arm mamba2/actors=8192. Runs go seed by seed, every arm of a seed "
            "before the next.",
        ),
    ] = None,
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
    settings: Settings,
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
    nproc: Annotated[
        int,
        typer.Option(
            "--nproc",
            min=1,
            help="Train each run data-parallel (DD-PPO) on this many ranks through torchrun, one GPU each, "
            "--actors per rank; rank 0 evaluates and its clock times the run.",
        ),
    ] = 1,
    resolution: ResolutionOpt = 512,
    corpus_root: Annotated[
        Path,
        typer.Option("--corpus-root", help="Where the split corpora are built (reused when present)."),
    ] = Path("artifacts/corpus/bench-learn"),
    openarena: OpenArenaOpt = DEFAULT_PK3,
    out: Annotated[
        Path | None, typer.Option("--out", help="Result folder (default artifacts/bench/learn/<time>).")
    ] = None,
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
    warmup_updates: Annotated[
        int,
        typer.Option(
            "--warmup-updates",
            min=0,
            help="Untimed PPO updates of every arm before the runs, outside their clocks: they fill the "
            "compile cache (0: none; the first run of each arm then compiles on its clock). With --nproc every "
            "run's ranks take them before it.",
        ),
    ] = 3,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as one JSON object.")] = False,
    record: RecordOpt = None,
    engine: EngineOpt = None,
) -> None:
    """Train from scratch on a train split, evaluate on unseen scenes during training; time to competence
    (explore: half the reactive baseline's collisions, 1.5x its coverage; pointgoal: success >= 0.9, SPL
    >= 0.75, fewer collisions per episode than the greedy baseline), learning curves (JSON + PNG)."""
    import time
    from dataclasses import replace

    import torch

    from navi_bench.learn import LearnConfig, RankRunError, bench_learn
    from navi_learner.envs.factory import parse_reward_overrides
    from navi_learner.evaluation.competence import EvalProtocol
    from navi_learner.evaluation.evaluate import jsonable

    try:
        overrides = parse_reward_overrides(reward or [])
    except ValueError as err:
        raise fail(str(err)) from err

    dev = pick_device(settings["device"])
    train = train_config(settings, dev, engine)
    cores = (
        tuple(a.strip() for a in arms)
        if arms
        else tuple(c.strip() for c in temporal_cores.split(",") if c.strip())
    )
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
        train=train,
        parallel=parallel,
        gpus=gpus,
        nproc=nproc,
        protocol=protocol,
        reward=tuple(overrides.items()),
        obstacles=obstacles,
        squad=squad,
        procedural_share=procedural_share,
        warmup_updates=warmup_updates,
    )
    folder = out or Path("artifacts/bench/learn") / time.strftime("%Y%m%d-%H%M%S")
    try:
        result = bench_learn(
            cfg, folder, dev, resolution, corpus_root, openarena, say=lambda m: typer.echo(m, err=True)
        )
    except (ValueError, RankRunError) as err:
        raise fail(str(err)) from err
    summary = {"out": str(folder), "summary": jsonable(result["summary"])}
    if record is not None:
        record_result(summary, "learn", dev, record)
    if as_json:
        typer.echo(json.dumps(summary))
    else:
        typer.echo((folder / "report.md").read_text())
        typer.echo(f"results: {folder}")


@app.command(name="transfer")
@config_options(
    learning_recipe(),
    LEARN_OPTIONS,
    defaults=COMMAND_DEVICE,
    helps={
        "n_actors": "Actors per run (0: 8,192 on CUDA, 2,048 on a GPU under 36 GiB, 8 on CPU).",
        "rollout_length": "Steps per rollout (0: 64 on CUDA, 32 on CPU).",
    },
)
def bench_transfer_cmd(
    *,
    arms: Annotated[
        list[str] | None,
        typer.Option(
            "--arm",
            help="What a run trains on (repeatable): procedural[:SEMANTICS[:FAMILY+FAMILY...]] (procedural "
            "scenes of seed 0; SEMANTICS object or surface; FAMILY@S scales that entry's scenes by up to S) or "
            "openarena (the maps outside the held-out fifth); either may end in /KEY=VALUE[,KEY=VALUE...]: "
            "train with those RewardConfig weights (or a fresh engine with those EngineConfig fields, e.g. "
            "action_input=1) replaced, or from init_from=CHECKPOINT's weights (explore or pointgoal: the "
            "shipped reference) in the engine it stored, on the same corpus. Default: procedural and openarena.",
        ),
    ] = None,
    seeds: Annotated[
        int, typer.Option("--seeds", min=1, help="Training seeds per arm (FIRST, FIRST+1, ...).")
    ] = 3,
    first_seed: Annotated[int, typer.Option("--first-seed", min=0, help="First training seed.")] = 0,
    budget: Annotated[float, typer.Option("--budget-s", min=1.0, help="Training seconds per run.")] = 240.0,
    settings: Settings,
    eval_actors: Annotated[
        int, typer.Option("--eval-actors", min=1, help="Actors per evaluation, spread over the scenes.")
    ] = 1000,
    eval_steps: Annotated[int, typer.Option("--eval-steps", min=1, help="Steps per evaluation.")] = 1000,
    episode_steps: Annotated[
        int, typer.Option("--eval-episode-steps", min=1, help="Episode length in evaluations.")
    ] = 500,
    gpus: Annotated[
        int,
        typer.Option(
            "--gpus", min=0, help="One run per GPU at a time on cuda:0.. (0: all runs on --device)."
        ),
    ] = 0,
    procedural_train: Annotated[
        int, typer.Option("--procedural-train", min=1, help="Procedural train scenes per arm.")
    ] = 16,
    openarena_maps: Annotated[
        int,
        typer.Option("--openarena-maps", min=0, help="Only the first N OpenArena maps by name (0: all 50)."),
    ] = 0,
    resolution: ResolutionOpt = 512,
    corpus_root: Annotated[
        Path,
        typer.Option("--corpus-root", help="Where the corpora are built (reused when present)."),
    ] = Path("artifacts/corpus/bench-transfer"),
    openarena: OpenArenaOpt = DEFAULT_PK3,
    out: Annotated[
        Path | None, typer.Option("--out", help="Result folder (default artifacts/bench/transfer/<time>).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as one JSON object.")] = False,
    action_noise: Annotated[
        list[float] | None,
        typer.Option(
            "--action-noise",
            min=0.0,
            help="Fly every final checkpoint once per value (repeatable): 0 its mean action, S > 0 its actions "
            "sampled with S times its learned std; each value but the task's own in a row of its own ('ARM, "
            "mean action', 'ARM, sampled xS'). Default: as the task is evaluated everywhere (explore 1, "
            "point-goal 0).",
        ),
    ] = None,
    record: RecordOpt = None,
    engine: EngineOpt = None,
) -> None:
    """Train on procedural scenes alone (and, as the upper reference, on real maps), then fly every final
    checkpoint on the OpenArena maps it never saw, per map, against the baselines; collisions broken down
    by the surface touched and counted as pinned from a drone's 10th contact step in a row. Each worker
    runs a few untimed updates first, so no run spends its budget compiling (docs/TRAINING.md, "Real maps
    never seen")."""
    from navi_bench.transfer import TransferConfig, bench_transfer, parse_arm
    from navi_learner.evaluation.competence import EvalProtocol
    from navi_learner.evaluation.evaluate import jsonable

    try:
        chosen = tuple(parse_arm(a) for a in (arms or ["procedural", "openarena"]))
    except ValueError as err:
        raise fail(str(err)) from err
    dev = pick_device(settings["device"])
    cfg = TransferConfig(
        arms=chosen,
        seeds=tuple(range(first_seed, first_seed + seeds)),
        budget_s=budget,
        train=train_config(settings, dev, engine),
        protocol=EvalProtocol(actors=eval_actors, steps=eval_steps, episode_steps=episode_steps),
        gpus=gpus,
        procedural_train=procedural_train,
        openarena_maps=openarena_maps,
        action_noise=tuple(dict.fromkeys(action_noise or [])),
    )
    folder = out or Path("artifacts/bench/transfer") / time.strftime("%Y%m%d-%H%M%S")
    try:
        result = bench_transfer(
            cfg, folder, dev, resolution, corpus_root, openarena, say=lambda m: typer.echo(m, err=True)
        )
    except ValueError as err:
        raise fail(str(err)) from err
    summary = {"out": str(folder), "summary": jsonable(result["summary"]["parts"]), "notes": result["notes"]}
    if record is not None:
        record_result(summary, "transfer", dev, record)
    if as_json:
        typer.echo(json.dumps(summary))
    else:
        typer.echo((folder / "report.md").read_text())
        typer.echo(f"results: {folder}")


@app.command(name="trainers")
def bench_trainers_cmd(
    corpus: Annotated[Path, typer.Option("--corpus", help="The train corpus folder.")],
    unseen: Annotated[
        Path, typer.Option("--unseen", help="The unseen corpus folder the trainers are judged on.")
    ],
    actors: Annotated[int, typer.Option("--actors", min=1, help="Drones every trainer trains on.")] = 2048,
    budget: Annotated[
        float, typer.Option("--budget-s", min=1.0, help="Training seconds per trainer at most.")
    ] = 600.0,
    eval_every: Annotated[
        float,
        typer.Option("--eval-every-s", min=1.0, help="Training seconds between two unseen evaluations."),
    ] = 30.0,
    trainers: Annotated[
        str, typer.Option("--trainers", help="Comma-separated: navi, rsl_rl, skrl, torchrl.")
    ] = "navi,rsl_rl,skrl,torchrl",
    seed: Annotated[int, typer.Option("--seed", help="Seed of every trainer and env.")] = 0,
    device: EnvDeviceOpt = "cuda",
    work_dir: Annotated[Path, typer.Option("--work-dir", help="Where Navi's own run folder goes.")] = Path(
        "artifacts/bench/trainers"
    ),
    as_json: JsonOutOpt = False,
    record: RecordOpt = None,
) -> None:
    """Train Navi's PPO and the stock trainers (rsl_rl, skrl, TorchRL; examples/) on the same drones and
    scenes, each until it beats the reactive avoider on the unseen corpus or the budget, with the env-steps/s
    each reaches (docs/ENVIRONMENT.md, "Trainers compared")."""
    from navi_bench.trainers import TRAINERS, bench_trainers

    chosen = [t.strip() for t in trainers.split(",") if t.strip()]
    unknown = sorted(set(chosen) - set(TRAINERS))
    if unknown or not chosen:
        raise fail(f"--trainers takes {', '.join(TRAINERS)}; got {trainers!r}")
    try:
        result = bench_trainers(
            corpus, unseen, work_dir, pick_device(device), actors=actors, budget_s=budget,
            eval_every_s=eval_every, trainers=chosen, seed=seed,
        )  # fmt: skip
    except (ValueError, RuntimeError) as err:
        raise fail(str(err)) from err
    if record is not None:
        record_result(result, "trainers", device, record)
    typer.echo(json.dumps(result) if as_json else "\n".join(f"{k}: {v}" for k, v in result.items()))


BENCH_TRAIN_OPTIONS = (
    "n_actors",
    "temporal_core",
    "device",
    "rollout_length",
    "compile",
    "compile_rollout",
    "compile_update",
    "update_graphs",
    "tf32",
    "obs_dtype",
    "max_minibatch",
    "rank_scenes",
)
"""The TrainConfig settings `navi bench train` takes as options."""


@app.command(name="train")
@config_options(TrainConfig(), BENCH_TRAIN_OPTIONS, defaults=COMMAND_DEVICE)
def bench_train_cmd(
    *,
    settings: Settings,
    corpus: CorpusOpt = None,
    env: EnvOpt = "sdfdag",
    updates: Annotated[int, typer.Option("--updates", help="Measured PPO updates (after 2 warm-up).")] = 5,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    record: RecordOpt = None,
    nproc: Annotated[
        int,
        typer.Option(
            "--nproc",
            min=1,
            help="Also measure N data-parallel ranks (torchrun, one per GPU, --actors each) after one "
            "process: per-rank and total SPS, scaling efficiency SPS(N) / (N x SPS(1)).",
        ),
    ] = 1,
    single_runs: Annotated[
        int,
        typer.Option(
            "--single-runs",
            min=1,
            max=2,
            help="With --nproc: one-process runs, before the ranks and (2) after them; SPS(1) is the faster.",
        ),
    ] = 2,
    result_file: Annotated[
        Path | None, typer.Option("--result-file", hidden=True, help="Write the JSON here instead.")
    ] = None,
    versus: Annotated[
        str | None,
        typer.Option(
            "--versus",
            help="Also measure this command with these options added (the variant, e.g. "
            "--versus='--no-update-graphs'), each run in a process of its own, the command as given and the "
            "variant in turn for --rounds rounds: both medians and their ratio. Not with --nproc or --profile.",
        ),
    ] = None,
    rounds: Annotated[
        int | None,
        typer.Option("--rounds", min=1, help="With --versus: runs of each, base and variant in turn (2)."),
    ] = None,
    engine: EngineOpt = None,
    profile: Annotated[
        Path | None,
        typer.Option(
            "--profile",
            help="Run one more update after the measured ones with its rollout and its PPO update under "
            "torch.profiler, and write there collect-TAG.txt and update-TAG.txt (TAG one-process or "
            "rankN): the kernels' busy time, then the operators by device time. With --nproc the last "
            "one-process run's files stay.",
        ),
    ] = None,
) -> None:
    """Env only / env + inference / env + training SPS and ms per stage."""
    from dataclasses import replace

    import torch

    from navi_bench.train import bench_train, bench_train_scaling, bench_train_versus
    from navi_learner.config import StorageError, default_actors
    from navi_learner.ppo import dist

    if rounds is not None and versus is None:
        raise fail("--rounds counts the runs of a --versus comparison: name --versus too")
    if versus is not None:
        if nproc > 1 or profile is not None:
            raise fail("--versus compares one-process runs: leave out --nproc and --profile")
        variant = shlex.split(versus)
        if not variant:
            raise fail("--versus needs the options that make the variant, e.g. --versus='--no-update-graphs'")
        args = sys.argv[1:]
        for name in ("--versus", "--rounds", "--record", "--result-file"):
            args = dist.strip_option(args, name)
        try:
            result = bench_train_versus(args, variant, rounds or 2)
        except RuntimeError as err:
            raise fail(str(err)) from err
    elif nproc > 1 and not dist.launched():
        args = dist.strip_option(dist.strip_option(sys.argv[1:], "--nproc"), "--result-file")
        try:
            result = bench_train_scaling(nproc, dist.strip_option(args, "--single-runs"), single_runs)
        except RuntimeError as err:
            raise fail(str(err)) from err
    else:
        try:
            d, dev = dist.setup(pick_device(settings["device"]))
        except ValueError as err:
            raise fail(str(err)) from err
        try:
            cfg = train_config(settings, dev, engine)
            n = cfg.n_actors or default_actors(torch.device(dev))
            environment = build_env(env, corpus, n, dev, d.rank, d.rank, d.world, rank_scenes=cfg.rank_scenes)
            cfg = replace(cfg, n_actors=n)
            result = bench_train(environment, cfg, updates=updates, dist=d, profile_dir=profile)
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
    if record is not None:
        record_result(result, "train", pick_device(settings["device"]), record)
    sys.stdout.flush()
