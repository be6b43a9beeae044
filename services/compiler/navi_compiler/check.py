"""`navi check`: validate .gmdag files and describe them (header, compression, degenerate fields)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from navi_compiler.gmdag import (
    FLAG_INSIDE_SEEDS,
    FLAG_LEAK_FALLBACK,
    TAG_BRICK,
    TAG_FAR_FREE,
    TAG_FAR_SOLID,
    Gmdag,
    GmdagError,
    decode_gmdag,
    leaf_cubes,
    payload_bytes,
)


@dataclass(frozen=True)
class CheckReport:
    """What `navi check` reports for one file. Fields past `error` are None for an invalid file."""

    path: str
    valid: bool
    error: str | None  # the reader's one-line error for an invalid file
    size_bytes: int
    resolution: int | None = None  # R, cells per edge
    voxel_size: float | None = None  # meters
    origin: tuple[float, float, float] | None = None  # cube min corner, meters
    cube_max: tuple[float, float, float] | None = None  # cube max corner, meters
    bounds_min: tuple[float, float, float] | None = None  # source geometry, meters
    bounds_max: tuple[float, float, float] | None = None
    band: float | None = None  # voxels
    quant_step: float | None = None  # voxels per i8 unit
    levels: int | None = None
    node_count: int | None = None
    brick_count: int | None = None
    spawn_count: int | None = None
    class_names: tuple[str, ...] | None = None
    inside_seeded: bool | None = None  # flags bit 0
    leak_fallback: bool | None = None  # flags bit 1: the fill leaked when the file was compiled
    version: int | None = None  # format version (1: raw payload, 2: zlib payload)
    payload_bytes: int | None = None  # the octree (nodes, bricks, classes) uncompressed, as held in memory
    compression: float | None = None  # dense float32 bytes (R^3 * 4) / file bytes
    memory_compression: float | None = None  # dense float32 bytes / payload_bytes
    non_finite: int | None = None  # non-finite header floats or spawn coordinates (0 in a valid file)
    has_free: bool | None = None  # some stored sample > 0 or a far-free code
    has_solid: bool | None = None  # some stored sample < 0 or a far-solid code
    degenerate: str | None = None  # "all void", "all solid" or None

    @property
    def ok(self) -> bool:
        """Valid and not degenerate."""
        return self.valid and self.degenerate is None


def _non_finite(g: Gmdag) -> int:
    floats = np.array([*g.origin, g.voxel_size, g.band, g.quant_step, *g.bounds_min, *g.bounds_max])  # (13,)
    return int((~np.isfinite(floats)).sum() + (~np.isfinite(g.spawns)).sum())


def describe(g: Gmdag, path: str, size: int, version: int) -> CheckReport:
    """The report of a decoded (hence valid) file of `size` bytes in format `version`."""
    words, _, _ = leaf_cubes(g)
    tags = words >> 30  # (M,)
    used = np.unique(words[tags == TAG_BRICK] & ((1 << 30) - 1))  # (U,) referenced bricks
    samples = g.bricks[used]  # (U, 729) int8
    has_free = bool((tags == TAG_FAR_FREE).any() or (samples > 0).any())
    has_solid = bool((tags == TAG_FAR_SOLID).any() or (samples < 0).any())
    degenerate = (
        "all solid" if not has_free else ("all void" if not has_solid and not (samples == 0).any() else None)
    )
    return CheckReport(
        path=path,
        valid=True,
        error=None,
        size_bytes=size,
        resolution=g.resolution,
        voxel_size=g.voxel_size,
        origin=g.origin,
        cube_max=g.cube_max,
        bounds_min=g.bounds_min,
        bounds_max=g.bounds_max,
        band=g.band,
        quant_step=g.quant_step,
        levels=g.levels,
        node_count=len(g.nodes),
        brick_count=len(g.bricks),
        spawn_count=len(g.spawns),
        class_names=g.class_names,
        inside_seeded=bool(g.flags & FLAG_INSIDE_SEEDS),
        leak_fallback=bool(g.flags & FLAG_LEAK_FALLBACK),
        version=version,
        payload_bytes=payload_bytes(len(g.nodes), len(g.bricks)),
        compression=g.resolution**3 * 4 / size,
        memory_compression=g.resolution**3 * 4 / payload_bytes(len(g.nodes), len(g.bricks)),
        non_finite=_non_finite(g),
        has_free=has_free,
        has_solid=has_solid,
        degenerate=degenerate,
    )


def check_file(path: str | os.PathLike[str]) -> CheckReport:
    """Read, validate and describe one file; never raises for a bad file (the report says why)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        return CheckReport(
            path=str(p), valid=False, error=f"cannot read: {exc.strerror or exc}", size_bytes=0
        )
    try:
        g = decode_gmdag(data)
    except GmdagError as exc:
        return CheckReport(path=str(p), valid=False, error=str(exc), size_bytes=len(data))
    return describe(g, str(p), len(data), int.from_bytes(data[8:12], "little"))
