"""Ingestion: any scene source -> `Scene` (world meters, +Z up).

Sources: triangle meshes (.glb/.gltf/.obj/.ply/.stl, through trimesh), Quake 3 maps (.bsp, IBSP
version 46) and .pk3 archives of maps (`maps.pk3` with a map name, or `maps.pk3:maps/name.bsp`).
Every failure on bad input raises `IngestError` (a ValueError). docs/SCENES.md has the rules.
Sources and archive members larger than `max_bytes` (default 256 MiB) fail with `SourceTooLargeError`
before they are read (navi_compiler.ingest.limits).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from navi_compiler.ingest.bsp import BspOptions, bsp_to_scene, parse_bsp, parse_entities
from navi_compiler.ingest.errors import IngestError
from navi_compiler.ingest.limits import (
    MAX_SOURCE_BYTES,
    SourceTooLargeError,
    check_file_size,
    read_file_capped,
)
from navi_compiler.ingest.mesh import MESH_SUFFIXES, MeshOptions, load_mesh
from navi_compiler.ingest.pk3 import list_pk3_maps, read_pk3_map
from navi_compiler.ingest.sidecar import Sidecar, read_sidecar, sidecar_path, write_sidecar
from navi_compiler.scene import Scene

__all__ = [
    "MAX_SOURCE_BYTES",
    "QUAKE3_SCALE",
    "IngestError",
    "Sidecar",
    "SourceTooLargeError",
    "list_pk3_maps",
    "load_scene",
    "read_entities",
    "read_sidecar",
    "sidecar_path",
    "write_sidecar",
]

QUAKE3_SCALE = 0.0254  # meters per Quake 3 unit (one inch)
_PK3_SEPARATOR = ".pk3:"


def _split_source(src: str | os.PathLike[str]) -> tuple[Path, str | None]:
    """'maps.pk3:maps/x.bsp' -> (maps.pk3, 'maps/x.bsp'); anything else -> (path, None)."""
    text = os.fspath(src)
    cut = text.lower().rfind(_PK3_SEPARATOR)
    if cut >= 0 and not Path(text).exists():
        end = cut + len(_PK3_SEPARATOR) - 1
        return Path(text[:end]), text[end + 1 :]
    return Path(text), None


def _read_map(
    src: str | os.PathLike[str], map_name: str | None, max_bytes: int = MAX_SOURCE_BYTES
) -> tuple[str, bytes]:
    """(map name, BSP bytes) from a .bsp file, a .pk3 plus map name, or 'archive.pk3:member'."""
    path, member = _split_source(src)
    suffix = path.suffix.lower()
    if member is not None:
        if map_name is not None and map_name != member:
            raise IngestError(f"two map names given: {member!r} in the source and {map_name!r}")
        return read_pk3_map(path, member, max_bytes)
    if not path.is_file():
        raise IngestError(f"scene source not found: {path}")
    if suffix == ".pk3":
        return read_pk3_map(path, map_name, max_bytes)
    if suffix == ".bsp":
        if map_name is not None:
            raise IngestError("a map name only applies to .pk3 archives")
        return path.stem, read_file_capped(path, max_bytes)
    raise IngestError(f"{path} is not a Quake 3 map (.bsp or .pk3)")


def read_entities(
    src: str | os.PathLike[str], *, map_name: str | None = None, max_bytes: int = MAX_SOURCE_BYTES
) -> list[dict[str, str]]:
    """The entity lump of a Quake 3 map (.bsp, .pk3 + map name, or 'archive.pk3:maps/x.bsp')."""
    _, raw = _read_map(src, map_name, max_bytes)
    return parse_entities(parse_bsp(raw).entities)


def load_scene(
    src: str | os.PathLike[str],
    *,
    map_name: str | None = None,
    scale: float | None = None,
    repair: bool = False,
    seeds: Sequence[tuple[float, float, float]] = (),
    max_bytes: int = MAX_SOURCE_BYTES,
) -> Scene:
    """Load any supported scene source as a Scene in world meters (+Z up).

    src: a mesh (.glb/.gltf/.obj/.ply/.stl), a .bsp, a .pk3 (with `map_name`, or alone when it
    holds one map) or 'archive.pk3:maps/name.bsp'. scale: meters per source unit (default 0.0254
    for Quake 3 maps, 1.0 for meshes). repair: mesh repair through trimesh (meshes only; BSP
    geometry is already in world space). seeds: extra known-free points, in meters. max_bytes: the
    size cap of the source file or archive member, checked before it is read (SourceTooLargeError).
    """
    extra = np.asarray(list(seeds), dtype=np.float64).reshape(-1, 3)  # (S, 3) meters
    if not np.isfinite(extra).all():
        raise IngestError("seeds must be finite (x, y, z) points in meters")
    path, member = _split_source(src)
    suffix = path.suffix.lower()
    if member is None and suffix in MESH_SUFFIXES:
        if map_name is not None:
            raise IngestError("a map name only applies to .pk3 archives")
        if not path.is_file():
            raise IngestError(f"scene source not found: {path}")
        check_file_size(path, max_bytes)
        return load_mesh(path, MeshOptions(scale=1.0 if scale is None else scale, repair=repair), extra)
    if member is None and suffix not in (".bsp", ".pk3"):
        known = ", ".join((*MESH_SUFFIXES, ".bsp", ".pk3"))
        raise IngestError(f"unknown scene format {suffix or '(none)'!r} for {path}; known: {known}")
    name, raw = _read_map(src, map_name, max_bytes)
    options = BspOptions(scale=QUAKE3_SCALE if scale is None else scale)
    return bsp_to_scene(parse_bsp(raw), name, options, extra)
