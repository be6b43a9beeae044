"""The `<stem>.scene.json` sidecar: what a plain mesh file cannot carry (classes, seeds, barriers).

A mesh written by `navi scenes generate` (or any tool) may sit next to `<stem>.scene.json`:

    {"format": "navi-scene", "version": 1,
     "faces": F,                                  # drawn triangles in the mesh, in file order
     "class_names": ["unknown", "floor", ...],    # id -> name, id 0 is "unknown"
     "face_class_runs": [[id, count], ...],       # run-length face classes, counts sum to F
     "seeds": [[x, y, z], ...],                   # known-free points, mesh units
     "barrier_vertices": [[x, y, z], ...],        # undrawn fill barriers, mesh units
     "barrier_faces": [[a, b, c], ...],           # triangles into barrier_vertices
     "obstacles": {"count": 6, "speed_max": 2.0}} # optional: moving obstacles this scene declares

`load_scene` picks it up for a mesh file and applies the same `scale` to seeds and barriers.

Shapes: F faces, S seeds, Vb barrier vertices, Fb barrier faces.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from navi_compiler.ingest.errors import IngestError

SIDECAR_FORMAT = "navi-scene"
SIDECAR_VERSION = 1
SIDECAR_SUFFIX = ".scene.json"
OBSTACLE_KEYS = ("count", "size_min", "size_max", "speed_min", "speed_max", "reach_min", "reach_max")
"""Moving-obstacle settings a scene may declare (the env's navi_env.sim.obstacles.SCENE_KEYS)."""


@dataclass(frozen=True)
class Sidecar:
    """Per-face classes, seeds and barrier geometry of one mesh file, in the mesh's own units."""

    face_class: np.ndarray  # (F,) uint8
    class_names: tuple[str, ...]
    seeds: np.ndarray  # (S, 3) float64
    barrier_vertices: np.ndarray  # (Vb, 3) float64
    barrier_faces: np.ndarray  # (Fb, 3) int64 into barrier_vertices
    obstacles: dict[str, float] = field(default_factory=dict)
    """Moving obstacles the scene declares (navi_env.sim.obstacles.SCENE_KEYS -> number; meters,
    m/s); the corpus manifest carries them to the env. Empty: the env's defaults."""


def sidecar_path(mesh_path: str | os.PathLike[str]) -> Path:
    """`dir/name.obj` -> `dir/name.scene.json`."""
    path = Path(mesh_path)
    return path.with_name(path.stem + SIDECAR_SUFFIX)


def _runs(values: np.ndarray) -> list[list[int]]:
    """Run-length encode (F,) ids as [[id, count], ...]."""
    if len(values) == 0:
        return []
    change = np.flatnonzero(np.diff(values.astype(np.int64))) + 1  # (R-1,)
    starts = np.concatenate([[0], change])  # (R,)
    lengths = np.diff(np.concatenate([starts, [len(values)]]))  # (R,)
    return [[int(values[s]), int(n)] for s, n in zip(starts, lengths, strict=True)]


def write_sidecar(mesh_path: str | os.PathLike[str], sidecar: Sidecar) -> Path:
    """Write the sidecar next to the mesh (rounded to 1e-6 units); returns its path."""
    payload = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "faces": len(sidecar.face_class),
        "class_names": list(sidecar.class_names),
        "face_class_runs": _runs(sidecar.face_class),
        "seeds": np.round(sidecar.seeds, 6).tolist(),
        "barrier_vertices": np.round(sidecar.barrier_vertices, 6).tolist(),
        "barrier_faces": sidecar.barrier_faces.astype(np.int64).tolist(),
    }
    if sidecar.obstacles:
        payload["obstacles"] = dict(sidecar.obstacles)
    path = sidecar_path(mesh_path)
    path.write_text(json.dumps(payload, separators=(",", ":")) + "\n", encoding="utf-8")
    return path


def _array(value: object, label: str, dtype: type, path: Path) -> np.ndarray:
    try:
        array: np.ndarray = np.asarray(value if value else np.zeros((0, 3)), dtype=dtype).reshape(
            -1, 3
        )  # (K, 3)
    except (TypeError, ValueError) as err:
        raise IngestError(f"{path}: {label} must be a list of [x, y, z] triples") from err
    return array


def read_sidecar(path: Path) -> Sidecar:
    """Parse and validate a sidecar; raises IngestError on anything inconsistent."""
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise IngestError(f"cannot read scene sidecar {path}: {err}") from err
    if not isinstance(payload, dict) or payload.get("format") != SIDECAR_FORMAT:
        raise IngestError(f"{path} is not a {SIDECAR_FORMAT!r} sidecar")
    if payload.get("version") != SIDECAR_VERSION:
        raise IngestError(f"{path}: sidecar version {payload.get('version')!r}, expected {SIDECAR_VERSION}")
    names = payload.get("class_names", ["unknown"])
    runs = payload.get("face_class_runs", [])
    faces = payload.get("faces")
    if not (
        isinstance(names, list) and names and all(isinstance(n, str) for n in names) and len(names) <= 256
    ):
        raise IngestError(f"{path}: class_names must be 1 to 256 strings")
    if not (isinstance(runs, list) and all(isinstance(r, list) and len(r) == 2 for r in runs)):
        raise IngestError(f"{path}: face_class_runs must be [[id, count], ...]")
    ids = np.array([r[0] for r in runs], dtype=np.int64)  # (R,)
    counts = np.array([r[1] for r in runs], dtype=np.int64)  # (R,)
    if (ids < 0).any() or (ids >= len(names)).any() or (counts < 0).any() or int(counts.sum()) != faces:
        raise IngestError(f"{path}: face classes do not cover exactly {faces} faces with known ids")
    seeds = _array(payload.get("seeds"), "seeds", float, path)  # (S, 3)
    barrier_vertices = _array(payload.get("barrier_vertices"), "barrier_vertices", float, path)  # (Vb, 3)
    barrier_faces = _array(payload.get("barrier_faces"), "barrier_faces", np.int64, path)  # (Fb, 3)
    if barrier_faces.size and (barrier_faces.min() < 0 or barrier_faces.max() >= len(barrier_vertices)):
        raise IngestError(f"{path}: barrier_faces index a vertex out of range")
    if not all(math.isfinite(x) for x in np.concatenate([seeds.ravel(), barrier_vertices.ravel()])):
        raise IngestError(f"{path}: seeds and barrier vertices must be finite")
    obstacles = payload.get("obstacles", {})
    if not (
        isinstance(obstacles, dict)
        and all(
            isinstance(k, str) and isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for k, v in obstacles.items()
        )
        and set(obstacles) <= set(OBSTACLE_KEYS)
    ):
        raise IngestError(f"{path}: obstacles must map some of {OBSTACLE_KEYS} to finite numbers")
    return Sidecar(
        obstacles={k: float(v) for k, v in obstacles.items()},
        face_class=np.repeat(ids, counts).astype(np.uint8),
        class_names=tuple(names),
        seeds=seeds,
        barrier_vertices=barrier_vertices,
        barrier_faces=barrier_faces,
    )
