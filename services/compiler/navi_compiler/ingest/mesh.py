"""Triangle meshes (.glb/.gltf/.obj/.ply/.stl) through trimesh, flattened to world space.

trimesh is imported lazily: the compiler's hot path imports numpy alone. Scene graphs are
flattened by `Scene.dump()`, which bakes every node's world transform into its geometry (the
fix for scenes whose geometry lives in local space under scale transforms). A `<stem>.scene.json`
sidecar next to the mesh supplies face classes, seeds and barriers (see sidecar.py).

Shapes: V vertices, F faces, S seeds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from navi_compiler.ingest.errors import IngestError
from navi_compiler.ingest.sidecar import Sidecar, read_sidecar, sidecar_path
from navi_compiler.scene import Scene

MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl")


@dataclass(frozen=True)
class MeshOptions:
    """How a mesh file becomes a scene."""

    scale: float = 1.0
    """Meters per mesh unit."""
    repair: bool = False
    """Merge duplicate vertices, drop degenerate and duplicate faces, fix normals, fill holes."""


def _flatten(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle mesh of the file in world space: (vertices (V, 3) float64, faces (F, 3) int64)."""
    import trimesh

    try:
        loaded = trimesh.load(str(path), force="scene", process=False)
    except Exception as err:  # trimesh raises many exception types for malformed files
        raise IngestError(f"cannot read mesh {path}: {type(err).__name__}: {err}") from err
    scene = loaded if isinstance(loaded, trimesh.Scene) else trimesh.Scene(loaded)
    meshes = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        raise IngestError(f"mesh {path} holds no triangles")
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])  # (G,)
    vertices = np.concatenate([np.asarray(m.vertices, np.float64) for m in meshes])  # (V, 3)
    faces = np.concatenate([np.asarray(m.faces, np.int64) + o for m, o in zip(meshes, offsets, strict=True)])
    return vertices, faces  # (V, 3) float64, (F, 3) int64


def _repair(
    vertices: np.ndarray, faces: np.ndarray, face_class: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """trimesh repair keeping each surviving face's class; filled holes get class 0 (unknown)."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.merge_vertices()
    keep = mesh.nondegenerate_faces() & mesh.unique_faces()  # (F,) bool
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    classes = face_class[keep]  # (F',) uint8
    trimesh.repair.fix_normals(mesh)
    mesh.fill_holes()
    added = len(mesh.faces) - len(classes)
    classes = np.concatenate([classes, np.zeros(added, np.uint8)])  # (F'',) uint8
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), classes


def load_mesh(path: Path, options: MeshOptions, extra_seeds: np.ndarray) -> Scene:
    """Load a mesh file (and its sidecar, if any) as a Scene in meters."""
    if options.scale <= 0 or not np.isfinite(options.scale):
        raise IngestError(f"scale must be a positive number of meters per unit, got {options.scale}")
    vertices, faces = _flatten(path)  # (V, 3), (F, 3)
    if not np.isfinite(vertices).all():
        raise IngestError(f"mesh {path} has non-finite vertex coordinates")
    side_path = sidecar_path(path)
    sidecar: Sidecar | None = read_sidecar(side_path) if side_path.is_file() else None
    if sidecar is not None and len(sidecar.face_class) != len(faces):
        raise IngestError(
            f"{side_path} describes {len(sidecar.face_class)} faces but {path} has {len(faces)}"
        )
    face_class = sidecar.face_class if sidecar is not None else np.zeros(len(faces), np.uint8)  # (F,)
    if options.repair:
        vertices, faces, face_class = _repair(vertices, faces, face_class)
    seeds = [np.asarray(extra_seeds, np.float64).reshape(-1, 3)]  # list of (S, 3) meters
    all_vertices = vertices * options.scale  # (V, 3) meters
    barrier = np.zeros((0, 3), np.int64)  # (Fb, 3)
    if sidecar is not None:
        seeds.insert(0, sidecar.seeds * options.scale)
        barrier = sidecar.barrier_faces + len(all_vertices)
        all_vertices = np.concatenate([all_vertices, sidecar.barrier_vertices * options.scale])
    return Scene(
        name=path.stem,
        vertices=np.ascontiguousarray(all_vertices, dtype=np.float64),
        faces=np.ascontiguousarray(faces, dtype=np.int64),
        face_class=np.ascontiguousarray(face_class, dtype=np.uint8),
        class_names=sidecar.class_names if sidecar is not None else ("unknown",),
        barrier_faces=barrier,
        seeds=np.ascontiguousarray(np.concatenate(seeds), dtype=np.float64),
    )
