"""Compiler commands: `navi compile` (a scene source to a .gmdag, here or on the compiler workers) and
`navi check` (validate and describe .gmdag files). Module-level imports: typer and the standard library."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from navi.commands.common import fail

if TYPE_CHECKING:
    from navi_compiler.compile import CompileStats
    from navi_compiler.gmdag import Gmdag
    from navi_compiler.scene import Scene

PANEL = "Compiler"
app = typer.Typer()
"""Merged into the root: `navi compile`, `navi check`."""


class EngineChoice(StrEnum):
    """Which compiler runs."""

    cpp = "cpp"
    ref = "ref"
    torch = "torch"


def _parse_seed(raw: str) -> tuple[float, float, float]:
    parts = raw.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(v == v and abs(v) != float("inf") for v in values):
        raise typer.BadParameter(f"--seed {raw!r} is not x,y,z (three finite numbers, meters)")
    return (values[0], values[1], values[2])


def _progress(enabled: bool) -> Callable[[str, float], None]:
    def report(stage: str, frac: float) -> None:
        if enabled:
            end = "\n" if frac >= 1.0 else ""
            sys.stderr.write(f"\r[navi compile] {frac * 100:5.1f}%  {stage:<28}{end}")
            sys.stderr.flush()

    return report


def load_source(
    src: str,
    map_name: str | None,
    scale: float | None,
    repair: bool,
    seeds: list[str] | None,
    max_bytes: int,
) -> Scene:
    """The scene a source holds (mesh, .bsp, .pk3 map), or a one-line error (exit 2)."""
    from navi_compiler.ingest import IngestError, load_scene

    points = [_parse_seed(s) for s in seeds or []]
    try:
        return load_scene(
            src, map_name=map_name, scale=scale, repair=repair, seeds=points, max_bytes=max_bytes
        )
    except (IngestError, OSError) as exc:
        raise fail(str(exc)) from None


def max_source_bytes(max_source_mb: float | None) -> int:
    """--max-source-mb in bytes, else NAVI_MAX_SOURCE_BYTES (default 256 MiB)."""
    if max_source_mb is not None:
        return max(1, int(max_source_mb * 2**20))
    from pydantic import ValidationError

    from navi_contracts.settings import NaviSettings

    try:
        return NaviSettings().max_source_bytes
    except ValidationError as err:
        raise fail(f"invalid NAVI_MAX_SOURCE_BYTES: {err.errors()[0]['msg']}") from None


def compile_summary(stats: dict[str, object], out: str | None, load_seconds: float) -> dict[str, object]:
    """The JSON summary of one compile: where it was written, how long loading took, the stats."""
    return {"output": out, "load_seconds": load_seconds, **stats}


def check_engine_device(engine: EngineChoice, device: str) -> None:
    """--device must name a usable torch device, and only goes with --engine torch."""
    if device == "cpu":
        return
    if engine != EngineChoice.torch:
        raise fail(f"--device {device} needs --engine torch")
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise fail(f"--device {device!r} is not a torch device") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise fail(f"--device {device}: CUDA is not available here")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise fail(f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) here")
    if dev.type not in ("cpu", "cuda"):
        raise fail(f"--device {device}: only cpu and cuda are supported")


def compile_or_fail(scene: Scene, resolution: int, **options: Any) -> tuple[Gmdag, CompileStats]:
    """compile_scene, with bad input and a lattice too large for memory as one-line errors (exit 2)."""
    from navi_compiler.compile import compile_scene

    try:
        return compile_scene(scene, resolution=resolution, **options)
    except ValueError as exc:
        raise fail(str(exc)) from None
    except MemoryError:
        raise fail(
            f"not enough memory for resolution {resolution} (about 20 bytes per lattice point)"
        ) from None


def _compile_remote(
    src: str,
    out: Path,
    resolution: int,
    scale: float | None,
    seed: list[str] | None,
    repair: bool,
    map_name: str | None,
    timeout: float,
    json_out: bool,
) -> None:
    """`navi compile --remote`: one CompileJob to a worker, its progress on stderr, its result."""
    import uuid

    from navi_compiler.service import submit_compile_job
    from navi_contracts.models import CompileJob
    from navi_mesh.pubsub import RequestError

    seeds = tuple(_parse_seed(s) for s in seed or ())
    try:
        job = CompileJob(
            job_id=uuid.uuid4().hex,
            source=src,
            output=str(out),
            resolution=resolution,
            scale=scale,
            map_name=map_name,
            seeds=seeds,
            repair=repair,
        )
    except ValueError as exc:
        raise fail(f"invalid job: {exc}") from None
    show = sys.stderr.isatty() and not json_out

    def on_progress(stage: str, fraction: float) -> None:
        if show:
            sys.stderr.write(f"\r[remote] {stage:<24} {100 * fraction:5.1f}%")
            sys.stderr.flush()

    try:
        result = submit_compile_job(job, timeout_s=timeout, on_progress=on_progress)
    except RequestError as exc:
        raise fail(f"remote compile failed: {exc}") from None
    if show:
        sys.stderr.write("\n")
    if not result.ok:
        raise fail(f"remote compile failed: {result.error_type}: {result.error}")
    if json_out:
        typer.echo(
            json.dumps(
                {
                    "output": result.output,
                    "worker": result.worker_id,
                    "seconds": result.duration_s,
                    **result.stats,
                }
            )
        )
        return
    typer.echo(f"{result.output}: compiled by worker {result.worker_id} in {result.duration_s:.1f} s")


@app.command("compile", rich_help_panel=PANEL)
def compile_cmd(
    src: Annotated[
        str, typer.Argument(help="Scene: .glb/.gltf/.obj/.ply/.stl, .bsp, .pk3 or maps.pk3:maps/x.bsp.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output .gmdag path (written atomically).")],
    resolution: Annotated[
        int, typer.Option(help="Cells per cube edge (rounded up to a power of two).")
    ] = 512,
    scale: Annotated[
        float | None,
        typer.Option(help="Meters per source unit (default 0.0254 for Quake 3, 1 for meshes)."),
    ] = None,
    seed: Annotated[
        list[str] | None, typer.Option("--seed", help="Known-free point x,y,z in meters (repeatable).")
    ] = None,
    repair: Annotated[
        bool, typer.Option(help="Repair meshes with trimesh (merge, fix normals, fill holes).")
    ] = False,
    map_name: Annotated[
        str | None, typer.Option("--map", help="Map name inside a .pk3 (e.g. oa_dm1).")
    ] = None,
    engine: Annotated[
        EngineChoice, typer.Option(help="cpp (fast), ref (NumPy) or torch (CPU/CUDA); same bytes.")
    ] = EngineChoice.cpp,
    threads: Annotated[int, typer.Option(help="C++ worker threads (0: all cores).", min=0)] = 0,
    device: Annotated[str, typer.Option(help="Torch device for --engine torch (cpu, cuda).")] = "cpu",
    json_out: Annotated[
        bool, typer.Option("--json", help="Print one JSON summary object on stdout.")
    ] = False,
    remote: Annotated[
        bool,
        typer.Option(
            "--remote",
            help="Submit the job to a `navi serve compiler` worker over Zenoh (NAVI_ZENOH_CONNECT) "
            "and wait for it; paths are as the worker sees them.",
        ),
    ] = False,
    timeout: Annotated[
        float, typer.Option(help="With --remote: seconds to wait for the worker's answer.", min=1.0)
    ] = 3600.0,
    band_m: Annotated[
        float,
        typer.Option(
            "--band-m",
            min=0.0,
            help="Meters from every surface within which the field is exact (the band widens to fit; "
            "0: the 4-voxel band alone). Navi's drones need 0.5.",
        ),
    ] = 0.5,
    max_source_mb: Annotated[
        float | None,
        typer.Option(
            "--max-source-mb",
            min=0.001,
            help="Largest source file or .pk3 member to read, MiB, checked before reading "
            "(default NAVI_MAX_SOURCE_BYTES, 256 MiB). With --remote the worker's own limit applies.",
        ),
    ] = None,
    keep_detached: Annotated[
        bool,
        typer.Option(
            "--keep-detached",
            help="Keep the parts of the scene that no seed reaches (scenery outside a sealed level); by "
            "default they are dropped so that the cube fits the level, unless the level then leaks.",
        ),
    ] = False,
    mesh_out: Annotated[
        Path | None,
        typer.Option(
            "--mesh-out",
            help="Also write the triangles the field measures to (drawn and barrier, world meters) as "
            "an .npz with `vertices` (V,3) float32 and `triangles` (F,3) int32: the --mesh of "
            "`navi bench trace --vs-warp`, so that Warp casts against the surfaces the tracer sees.",
        ),
    ] = None,
) -> None:
    """Compile a scene into a .gmdag signed-distance DAG."""
    from navi_compiler.gmdag import write_gmdag
    from navi_compiler.scene import write_surface_mesh

    check_engine_device(engine, device)
    if mesh_out is not None and (remote or mesh_out.suffix.lower() != ".npz"):
        raise fail("--mesh-out needs a local compile and a path ending in .npz")
    if mesh_out is not None and not mesh_out.parent.exists():
        raise fail(f"output folder {mesh_out.parent} does not exist")
    if remote:
        _compile_remote(src, out, resolution, scale, seed, repair, map_name, timeout, json_out)
        return
    t0 = time.perf_counter()
    scene = load_source(src, map_name, scale, repair, seed, max_source_bytes(max_source_mb))
    load_seconds = time.perf_counter() - t0
    show = sys.stderr.isatty() and not json_out
    g, stats = compile_or_fail(
        scene,
        resolution=resolution,
        min_band_m=band_m,
        engine=engine.value,
        threads=threads,
        progress=_progress(show),
        device=device,
        detached=not keep_detached,
    )
    if not out.parent.exists():
        raise fail(f"output folder {out.parent} does not exist")
    write_gmdag(g, out)
    if mesh_out is not None:
        from navi_compiler.ingest.detached import drop_detached

        write_surface_mesh(drop_detached(scene)[0] if stats.detached_parts else scene, mesh_out)
    summary = compile_summary(asdict(stats), str(out), load_seconds)
    if json_out:
        typer.echo(json.dumps(summary))
        return
    leak = (
        "LEAKED (fell back to outside seeding)"
        if stats.leaked
        else (f"ok ({stats.seeds_used} inside seed(s))" if stats.seeds_used else "ok (filled from outside)")
    )
    typer.echo(
        f"{out}: {stats.file_bytes / 1e6:.2f} MB, {stats.compression:.1f}x smaller than dense float32 "
        f"({stats.dense_bytes / 1e6:.0f} MB); octree in memory {stats.payload_bytes / 1e6:.2f} MB "
        f"({stats.memory_compression:.1f}x)\n"
        f"  resolution {stats.resolution}^3, voxel {stats.voxel_size:.4f} m, "
        f"{stats.node_count} nodes, {stats.brick_count} bricks\n"
        f"  leak check: {leak}\n"
        + (
            f"  dropped {stats.detached_parts} detached part(s), {stats.detached_triangles} triangles that no "
            "seed reaches (--keep-detached keeps them)\n"
            if stats.detached_parts
            else ""
        )
        + f"  time: {stats.seconds_total + load_seconds:.1f} s (load {load_seconds:.1f}, "
        f"sdf {stats.seconds_sdf:.1f}, dag {stats.seconds_dag:.1f}; engine {stats.engine})"
    )


@app.command("check", rich_help_panel=PANEL)
def check_cmd(
    files: Annotated[list[Path], typer.Argument(help=".gmdag files to validate.")],
    json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")] = False,
) -> None:
    """Validate .gmdag files and print their header, compression and degenerate-scene checks."""
    from navi_compiler.check import check_file

    reports = [check_file(f) for f in files]
    if json_out:
        typer.echo(
            json.dumps({"files": [asdict(r) for r in reports], "valid": all(r.valid for r in reports)})
        )
    else:
        for r in reports:
            if not r.valid:
                typer.echo(f"{r.path}: INVALID: {r.error}")
                continue
            note = f"  WARNING: degenerate scene ({r.degenerate})" if r.degenerate else ""
            typer.echo(
                f"{r.path}: valid, resolution {r.resolution}, voxel_size {r.voxel_size:.6g} m, "
                f"origin {tuple(round(v, 4) for v in r.origin or ())}, {r.node_count} nodes, "
                f"{r.brick_count} bricks, {r.spawn_count} spawns, format v{r.version}, "
                f"{r.compression:.1f}x vs dense float32 ({r.memory_compression:.1f}x in memory), "
                f"non-finite values {r.non_finite}, leak fallback {r.leak_fallback}{note}"
            )
    if not all(r.valid for r in reports):
        raise typer.Exit(1)
