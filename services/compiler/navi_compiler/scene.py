"""The in-memory scene every ingestion path produces and the SDF stage consumes.

Shapes: V vertices, F drawn faces, Fb barrier faces, S seeds. Coordinates are world meters.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Scene:
    """Triangles in world meters, ready for the signed-distance stage.

    `faces` are the drawn surfaces: distances are measured to them. `barrier_faces` bound the
    flyable space without being drawn (Quake 3 sky and the solid brushes of model 0): they block
    the inside/outside flood fill only. `seeds` are points known to be in free space (spawn
    points, `--seed`); with none, the fill starts from outside the cube (closed objects).
    """

    name: str
    vertices: np.ndarray  # (V, 3) float64, meters
    faces: np.ndarray  # (F, 3) int64 indices into vertices
    face_class: np.ndarray  # (F,) uint8 class id per drawn face (0 = unknown)
    class_names: tuple[str, ...] = ("unknown",)  # id -> name; id 0 is "unknown"
    barrier_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))  # (Fb, 3) int64
    seeds: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float64))  # (S, 3) float64, meters

    def __post_init__(self) -> None:
        v, f, fb, s = self.vertices, self.faces, self.barrier_faces, self.seeds
        if v.ndim != 2 or v.shape[1] != 3 or v.dtype != np.float64:
            raise ValueError(f"vertices must be (V, 3) float64, got {v.shape} {v.dtype}")
        for label, arr in (("faces", f), ("barrier_faces", fb)):
            if arr.ndim != 2 or arr.shape[1] != 3 or arr.dtype != np.int64:
                raise ValueError(f"{label} must be (F, 3) int64, got {arr.shape} {arr.dtype}")
            if arr.size and (arr.min() < 0 or arr.max() >= len(v)):
                raise ValueError(f"{label} index a vertex out of range")
        if self.face_class.shape != (len(f),) or self.face_class.dtype != np.uint8:
            raise ValueError("face_class must be (F,) uint8")
        if self.face_class.size and int(self.face_class.max()) >= len(self.class_names):
            raise ValueError("face_class holds an id without a class name")
        if s.ndim != 2 or s.shape[1] != 3 or s.dtype != np.float64:
            raise ValueError(f"seeds must be (S, 3) float64, got {s.shape} {s.dtype}")
        if not np.isfinite(v).all() or not np.isfinite(s).all():
            raise ValueError("vertices and seeds must be finite")
        if len(f) == 0:
            raise ValueError(f"scene {self.name!r} has no drawn triangles")

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box of every vertex used by a drawn or barrier face: ((3,), (3,)) meters."""
        used = np.unique(np.concatenate([self.faces.ravel(), self.barrier_faces.ravel()]))  # (U,)
        pts = self.vertices[used]  # (U, 3)
        return pts.min(axis=0), pts.max(axis=0)

    def surface_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Every triangle the field measures distances to, drawn and barrier alike (the surfaces a
        traced ray can end on): vertices (V, 3) float32 meters and triangles (F + Fb, 3) int32."""
        triangles = np.concatenate([self.faces, self.barrier_faces])  # (F + Fb, 3) int64
        if len(self.vertices) >= 2**31:
            raise ValueError(f"scene {self.name!r}: {len(self.vertices)} vertices do not fit int32 indices")
        return self.vertices.astype(np.float32), triangles.astype(np.int32)


def write_surface_mesh(scene: Scene, path: str | os.PathLike[str]) -> Path:
    """Write `scene.surface_mesh()` as an .npz (arrays `vertices`, `triangles`), the mesh that
    `navi bench trace --vs-warp --mesh` casts the benchmark's rays against. Atomic (temp file, then
    rename); the folder must exist."""
    out = Path(path)
    if out.suffix.lower() != ".npz":
        raise ValueError(f"the surface mesh is written as .npz, not {out.suffix or '(none)'!r}")
    vertices, triangles = scene.surface_mesh()  # (V, 3) float32, (T, 3) int32
    tmp = out.with_name(out.name + ".tmp")
    try:
        with tmp.open("wb") as f:
            np.savez_compressed(f, vertices=vertices, triangles=triangles)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out
