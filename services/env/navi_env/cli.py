"""`navi` sub-commands of navi_env (registered by navi.cli): `navi raycast`, `navi bench trace`, and the
environment's commands from cli_env."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from navi_env import cli_env
from navi_env.config import EnvConfig

TRACER = "Tracer"


def _fail(message: str) -> typer.Exit:
    typer.echo(f"error: {message}", err=True)
    return typer.Exit(2)


def raycast(
    gmdag: Annotated[Path, typer.Argument(help="Scene file (.gmdag).")],
    origins: Annotated[
        Path, typer.Option("--origins", help="(N, 3) float32 .npy of ray origins, world meters.")
    ],
    dirs: Annotated[
        Path, typer.Option("--dirs", help="(N, R, 3) or (R, 3) float32 .npy of unit directions.")
    ],
    out: Annotated[Path, typer.Option("-o", "--out", help="Where to write the (N, R) float32 depth .npy.")],
    device: Annotated[str, typer.Option(help="cpu, cuda or cuda:N.")] = "cpu",
    max_steps: Annotated[int, typer.Option(help="Sphere-tracing steps per ray.")] = 256,
    horizon: Annotated[float, typer.Option(help="Meters; a miss reports this depth.")] = 100.0,
    semantic_out: Annotated[
        Path | None,
        typer.Option("--semantic-out", help="Also write (N, R) int32 semantic (0 miss, 1+class)."),
    ] = None,
) -> None:
    """Depth along your own rays through a .gmdag scene (horizon on a miss)."""
    import numpy as np
    import torch

    from navi_compiler.gmdag import GmdagError
    from navi_env.scene import load_scene
    from navi_env.trace import trace

    try:
        o = np.load(origins)  # (N, 3)
        d = np.load(dirs)  # (N, R, 3) or (R, 3)
    except (OSError, ValueError) as exc:
        raise _fail(f"cannot read the .npy inputs: {exc}") from None
    if o.ndim != 2 or o.shape[1] != 3:
        raise _fail(f"--origins must be (N, 3), got {o.shape}")
    if not (d.ndim == 2 and d.shape[1] == 3) and not (
        d.ndim == 3 and d.shape[0] == o.shape[0] and d.shape[2] == 3
    ):
        raise _fail(f"--dirs must be (R, 3) or ({o.shape[0]}, R, 3), got {d.shape}")
    try:
        dev = torch.device(device)
        corpus = load_scene(gmdag, dev)
    except (OSError, GmdagError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    n, r = o.shape[0], d.shape[-2]
    depth = torch.empty(n, r, device=dev)  # (N, R) float32
    sem = torch.empty(n, r, dtype=torch.int32, device=dev)  # (N, R) int32
    try:
        trace(
            corpus,
            torch.zeros(n, dtype=torch.int64, device=dev),
            torch.from_numpy(np.ascontiguousarray(o, np.float32)).to(dev),
            torch.from_numpy(np.ascontiguousarray(d, np.float32)).to(dev),
            out_depth=depth,
            out_semantic=sem,
            max_steps=max_steps,
            horizon=horizon,
        )
    except (ValueError, TypeError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    np.save(out, depth.cpu().numpy())
    if semantic_out is not None:
        np.save(semantic_out, sem.cpu().numpy())
    hits = float((sem > 0).float().mean())
    typer.echo(f"wrote {out} ({n} x {r} depths, {hits:.1%} hits)", err=True)


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
    tiled: Annotated[
        bool,
        typer.Option("--tiled/--no-tiled", help="Schedule rays in 16x2 direction tiles (coherent warps)."),
    ] = True,
    vs_warp: Annotated[
        bool, typer.Option("--vs-warp", help="Also cast the same rays with a Warp mesh BVH.")
    ] = False,
    mesh: Annotated[
        Path | None,
        typer.Option(help="Source mesh for --vs-warp: .npz with vertices (V,3), triangles (F,3)."),
    ] = None,
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
) -> None:
    """G rays/s and observations/s of the tracer with the 256x48 spherical pattern."""
    from navi_compiler.gmdag import GmdagError
    from navi_env.bench_trace import TraceBenchConfig, bench_trace, bench_trace_maps
    from navi_env.scene import load_scene

    if agents < 1 or steps < 1:
        raise _fail("--agents and --steps must be at least 1")
    if not 0.0 <= hit_slope < 1.0:
        raise _fail(f"--hit-slope must be in [0, 1), got {hit_slope}")
    if (gmdag is None) == (corpus_dir is None):
        raise _fail("give one of --gmdag FILE or --corpus DIR")
    if vs_warp and mesh is None:
        raise _fail("--vs-warp needs --mesh FILE.npz (vertices, triangles) of the scene's source mesh")
    cfg = TraceBenchConfig(
        agents=agents, device=device, launches=steps, azimuth_bins=azimuth, elevation_bins=elevation,
        max_steps=max_steps, tiled_order=tiled, obstacles=obstacles, hit_slope=hit_slope,
    )  # fmt: skip
    if corpus_dir is not None:
        if vs_warp:
            raise _fail("--vs-warp needs one scene (--gmdag)")
        paths = sorted(corpus_dir.glob("*.gmdag")) if corpus_dir.is_dir() else []
        if not paths:
            raise _fail(f"{corpus_dir} holds no .gmdag files")
        try:
            report = bench_trace_maps(paths, cfg, lambda line: typer.echo(line, err=True))
        except (OSError, GmdagError, ValueError, RuntimeError) as exc:
            raise _fail(str(exc)) from None
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
            from navi_env.bench_warp import WarpUnavailable, bench_warp

            try:
                result["warp"] = bench_warp(corpus, cfg, mesh, measured.ms_per_launch)
            except WarpUnavailable as exc:
                result["warp"] = {"error": str(exc)}
                typer.echo(f"--vs-warp skipped: {exc}", err=True)
    except (OSError, GmdagError, ValueError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    if as_json:
        sys.stdout.write(json.dumps(result) + "\n")
        return
    for key, value in result.items():
        typer.echo(f"{key:>20}: {value}")


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add this package's commands to the root app and the `bench` group."""
    app.command("raycast", rich_help_panel=TRACER)(raycast)
    bench.command("trace", rich_help_panel=TRACER)(bench_trace_cmd)
    cli_env.register(app, bench)
