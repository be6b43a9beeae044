"""The compiler: Scene -> Gmdag. Placement (grid.py), signed field (sdf.py / the C++ core), DAG (dag.py).

`engine="cpp"` runs the C++17 core (navi_compiler._core), `engine="ref"` the NumPy reference; both
produce byte-identical files for the same scene and options. `engine="torch"` runs the PyTorch stages
(sdf_torch.py) on `device` (CPU or CUDA), also to the same bytes.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from navi_compiler.dag.build import DagArrays, build_dag, make_gmdag
from navi_compiler.gmdag import FLAG_LEAK_FALLBACK, Gmdag, encode_gmdag, payload_bytes, quant_step_for
from navi_compiler.ingest.detached import drop_detached
from navi_compiler.scene import Scene
from navi_compiler.sdf.grid import place, to_voxels
from navi_compiler.sdf.reference import SdfInput, SdfResult, signed_field_ref

log = logging.getLogger(__name__)

Engine = Literal["cpp", "ref", "torch"]
Progress = Callable[[str, float], None]  # (stage name, fraction of the whole compile done)


@dataclass(frozen=True)
class CompileStats:
    """What a compile did and produced."""

    resolution: int  # R
    voxel_size: float  # meters
    origin: tuple[float, float, float]  # cube min corner, meters
    triangles: int  # drawn triangles
    barrier_triangles: int  # barrier triangles
    seeds_given: int  # scene seeds + extra seeds
    seeds_used: int  # seeds that started the fill (0: filled from the border)
    leaked: bool  # seeded from inside, the fill reached the border and fell back to the border
    wall_points: int  # lattice points within 1/2 voxel of a surface
    free_fraction: float  # share of lattice points with a positive sign
    node_count: int
    brick_count: int
    file_bytes: int  # size of the encoded .gmdag (format version 2: zlib payload)
    payload_bytes: int  # the octree (nodes, bricks, classes) uncompressed, as a tracer holds it
    dense_bytes: int  # R^3 * 4, a dense float32 grid
    compression: float  # dense_bytes / file_bytes
    memory_compression: float  # dense_bytes / payload_bytes
    seconds_sdf: float  # signed field stage (engine torch: also its DAG, stage_seconds["dag"])
    seconds_dag: float  # DAG stage (engine torch: the file assembly only)
    seconds_total: float
    stage_seconds: dict[str, float]  # signed-field stages (distance, ..., classes; torch: + upload, dag)
    engine: str  # "cpp", "ref" or "torch"
    detached_parts: int = 0  # parts dropped as unreachable (navi_compiler.ingest.detached)
    detached_triangles: int = 0  # their drawn and barrier triangles


def _corners(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(vertices[faces])  # (F, 3, 3) float64


def _signed_field_cpp(inp: SdfInput, threads: int) -> SdfResult:
    from navi_compiler import _core  # type: ignore[attr-defined]

    lattice, brick_class, flags, seeds_used, wall_points, free_points, seconds = _core.signed_field(
        inp.drawn, inp.face_class, inp.barrier, inp.seeds, inp.resolution, float(inp.band), threads
    )
    log.debug("C++ signed-field stages (s): %s", seconds)
    return SdfResult(lattice, brick_class, flags, seeds_used, wall_points, free_points, seconds)


def _dag_cpp(sdf: SdfResult, band: float, threads: int) -> DagArrays:
    from navi_compiler import _core  # type: ignore[attr-defined]

    root, levels, nodes, bricks, brick_class = _core.build_dag(
        sdf.lattice, sdf.brick_class, float(band), quant_step_for(band), threads
    )
    return DagArrays(root, levels, nodes, bricks, brick_class)


def _compile_torch(inp: SdfInput, device: str) -> tuple[SdfResult, DagArrays]:
    """The torch engine runs the DAG's device half too; its lattice is not kept (an empty array)."""
    from navi_compiler.sdf.torch_engine import TorchConfig, compile_torch

    out = compile_torch(inp, TorchConfig(device=device))
    empty = np.zeros((0, 0, 0), np.float32)  # (0, 0, 0) float32
    sdf = SdfResult(
        empty,
        np.zeros((0, 0, 0), np.uint8),
        out.flags,
        out.seeds_used,
        out.wall_points,
        out.free_points,
        out.stage_seconds,
    )
    return sdf, out.arrays


FIT_RULES = 2
"""How compile_scene fits its cube round a scene: 1, round every vertex; 2, round what is left once the
parts no seed reaches are dropped (detached=True). Corpus manifests record it, and the commands that
reuse a corpus folder of real maps rebuild one made under other rules."""

EXACT_DISTANCE_M = 0.5
"""Meters from every surface within which a compiled field is exact by default: the drone physics must
tell a 0.3 m contact apart and certify a full-speed 0.5 m step (navi_env.sim.physics), which a far cube's
bound can do only if it is at least 0.4 m."""


def band_for(band: float, min_band_m: float, voxel_size: float) -> float:
    """The band (voxels) that keeps the field exact min_band_m meters out: at least `band`, widened in
    steps of 1/8 voxel until (band - sqrt(3)/2) * voxel_size >= min_band_m."""
    need = min_band_m / voxel_size + math.sqrt(3.0) / 2.0
    return max(band, math.ceil(need * 8.0) / 8.0) if min_band_m > 0 else band


def compile_scene(
    scene: Scene,
    *,
    resolution: int = 512,
    padding: int = 2,
    band: float = 4.0,
    min_band_m: float = EXACT_DISTANCE_M,
    seeds: Sequence[Sequence[float]] = (),
    engine: Engine = "cpp",
    threads: int = 0,
    progress: Progress | None = None,
    device: str = "cpu",
    detached: bool = True,
) -> tuple[Gmdag, CompileStats]:
    """Compile a scene into a validated Gmdag.

    resolution: cells per cube edge, rounded up to a power of two. padding: free cells kept on each
    side of the scene's longest axis. band: voxels of quantised distance kept around the surface.
    min_band_m: the band is widened (in steps of 1/8 voxel) so that the field is exact at least this
    many meters from every surface, i.e. (band - sqrt(3)/2) * voxel >= min_band_m: a far cube then
    certifies at least min_band_m of clearance (navi_env needs the drone radius plus half a step).
    seeds: extra known-free points (meters) added to scene.seeds. engine: "cpp", "ref" or "torch".
    threads: C++ worker threads (0: all cores; the output does not depend on it).
    progress: called with (stage, fraction done). device: torch device of engine="torch".
    detached: first drop the parts no seed can reach (navi_compiler.ingest.detached), so that the cube
    fits the level; if the fill from the seeds then reaches the smaller cube's border, the whole scene
    is compiled instead. The stats say what was dropped.
    """
    all_seeds = np.concatenate([scene.seeds, np.asarray(seeds, np.float64).reshape(-1, 3)])  # (S, 3) meters
    t0 = time.perf_counter()
    kept, dropped = drop_detached(scene, all_seeds) if detached else (scene, None)
    args = (resolution, padding, band, min_band_m, all_seeds, engine, threads, progress, device)
    if dropped is not None:
        g, stats = _compile_one(kept, *args, trial=True)
        if not stats.leaked:
            log.info(
                "scene %r: dropped %d detached part(s) (%d drawn, %d barrier triangles) that no seed "
                "reaches; the cube's longest side %.1f -> %.1f m",
                scene.name,
                dropped.parts,
                dropped.faces,
                dropped.barrier_faces,
                float((dropped.bounds_before[1] - dropped.bounds_before[0]).max()),
                float((dropped.bounds_after[1] - dropped.bounds_after[0]).max()),
            )
            return g, replace(
                stats,
                detached_parts=dropped.parts,
                detached_triangles=dropped.faces + dropped.barrier_faces,
                seconds_total=time.perf_counter() - t0,
            )
    g, stats = _compile_one(scene, *args)
    return g, replace(stats, seconds_total=time.perf_counter() - t0)


def _compile_one(
    scene: Scene,
    resolution: int,
    padding: int,
    band: float,
    min_band_m: float,
    all_seeds: np.ndarray,
    engine: Engine,
    threads: int,
    progress: Progress | None,
    device: str,
    trial: bool = False,
) -> tuple[Gmdag, CompileStats]:
    """compile_scene on exactly this scene and these seeds ((S, 3) meters). trial: the scene without its
    detached parts, which compile_scene replaces by the whole scene if it leaks (no leak warning then)."""
    report = progress or (lambda stage, frac: None)
    t0 = time.perf_counter()
    lo, hi = scene.bounds
    placement = place(lo, hi, resolution, padding)
    band = band_for(band, min_band_m, placement.voxel_size)
    inp = SdfInput(
        resolution=placement.resolution,
        drawn=to_voxels(_corners(scene.vertices, scene.faces), placement),
        face_class=np.ascontiguousarray(scene.face_class),
        barrier=to_voxels(_corners(scene.vertices, scene.barrier_faces), placement),
        seeds=to_voxels(all_seeds, placement),
        band=band,
    )
    report("signed distance field", 0.0)
    if engine == "torch":
        sdf, arrays = _compile_torch(inp, device)
    else:
        sdf = _signed_field_cpp(inp, threads) if engine == "cpp" else signed_field_ref(inp)
    if sdf.flags & FLAG_LEAK_FALLBACK and trial:
        log.info("scene %r: without its detached parts the fill leaks; compiling the whole scene", scene.name)
    elif sdf.flags & FLAG_LEAK_FALLBACK:
        log.warning(
            "scene %r: the fill from %d inside seed(s) reached the cube border (the scene leaks); "
            "fell back to filling from outside the cube",
            scene.name,
            sdf.seeds_used,
        )
    elif len(all_seeds) and not sdf.seeds_used:
        log.warning("scene %r: no seed lies in free space inside the cube; filled from outside", scene.name)
    t1 = time.perf_counter()
    report("DAG compression", 0.8)
    cube_lo = np.array(placement.origin)  # (3,)
    cube_hi = cube_lo + placement.resolution * placement.voxel_size  # (3,)
    inside = ((all_seeds >= cube_lo) & (all_seeds <= cube_hi)).all(axis=1)  # (S,)
    if engine == "cpp":
        arrays = _dag_cpp(sdf, band, threads)
    elif engine == "ref":
        arrays = build_dag(sdf.lattice, band, sdf.brick_class)
    g = make_gmdag(
        arrays,
        origin=placement.origin,
        voxel_size=placement.voxel_size,
        band=band,
        spawns=all_seeds[inside],
        class_names=scene.class_names,
        bounds=(tuple(lo.tolist()), tuple(hi.tolist())),
        flags=sdf.flags,
    )
    t2 = time.perf_counter()
    file_bytes = len(encode_gmdag(g))
    raw_bytes = payload_bytes(len(g.nodes), len(g.bricks))
    dense = placement.resolution**3 * 4
    report("done", 1.0)
    n_lattice = (placement.resolution + 1) ** 3
    stats = CompileStats(
        resolution=placement.resolution,
        voxel_size=placement.voxel_size,
        origin=placement.origin,
        triangles=len(scene.faces),
        barrier_triangles=len(scene.barrier_faces),
        seeds_given=len(all_seeds),
        seeds_used=sdf.seeds_used,
        leaked=bool(sdf.flags & FLAG_LEAK_FALLBACK),
        wall_points=sdf.wall_points,
        free_fraction=sdf.free_points / n_lattice,
        node_count=len(g.nodes),
        brick_count=len(g.bricks),
        file_bytes=file_bytes,
        payload_bytes=raw_bytes,
        dense_bytes=dense,
        compression=dense / file_bytes,
        memory_compression=dense / raw_bytes,
        seconds_sdf=t1 - t0,
        seconds_dag=t2 - t1,
        seconds_total=time.perf_counter() - t0,
        stage_seconds=dict(sdf.stage_seconds),
        engine=engine,
    )
    return g, stats
