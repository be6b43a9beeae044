"""Quake 3 Bézier patches: split a face's control grid into biquadratic 3×3 patches and tessellate them.

A patch face holds a (height × width) grid of control vertices, width = size[0] varying fastest,
both odd. Patch (a, b) of the face uses grid rows 2a..2a+2 and columns 2b..2b+2; neighbouring
patches share their edge row/column. The surface is
    P(u, v) = Σ_i Σ_j B_i(v) B_j(u) C[i, j],   B = ((1-t)², 2t(1-t), t²),
sampled on a (level + 1)² grid per patch.

Shapes: P patches, Kp patch faces, L level, Vp tessellated vertices, Tp triangles.
"""

from __future__ import annotations

import numpy as np

from navi_compiler.ingest.errors import IngestError


def patch_control_grids(
    faces: np.ndarray, positions: np.ndarray, normals: np.ndarray, patch_ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 3×3 control points of every patch of the given faces.

    faces: (Fq,) BSP face records; positions/normals: (Vq, 3) float64; patch_ids: (Kp,) face ids.
    Returns (control (P, 3, 3, 3), control normals (P, 3, 3, 3), owning face id (P,) int64).
    """
    chosen = faces[patch_ids]  # (Kp,)
    width = chosen["size"][:, 0].astype(np.int64)  # (Kp,)
    height = chosen["size"][:, 1].astype(np.int64)  # (Kp,)
    bad = (
        (width < 3)
        | (height < 3)
        | (width % 2 == 0)
        | (height % 2 == 0)
        | (width * height > chosen["n_vertices"])
    )
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise IngestError(
            f"BSP patch face {int(patch_ids[i])} has a {int(width[i])}×{int(height[i])} control grid "
            f"for {int(chosen['n_vertices'][i])} vertices (sides must be odd and >= 3)"
        )
    across, down = (width - 1) // 2, (height - 1) // 2  # (Kp,) patches per row / column
    per_face = across * down  # (Kp,)
    owner = np.repeat(np.arange(len(chosen)), per_face)  # (P,) index into chosen
    k = np.arange(int(per_face.sum())) - np.repeat(np.cumsum(per_face) - per_face, per_face)  # (P,)
    row, col = k // across[owner], k % across[owner]  # (P,) each
    base = chosen["vertex"][owner].astype(np.int64) + 2 * row * width[owner] + 2 * col  # (P,)
    offsets = np.arange(3)
    index = (
        base[:, None, None] + offsets[None, :, None] * width[owner][:, None, None] + offsets[None, None, :]
    )  # (P, 3, 3) into positions
    return positions[index], normals[index], patch_ids[owner].astype(np.int64)


def bernstein(level: int) -> np.ndarray:
    """Quadratic Bernstein weights at level + 1 evenly spaced t in [0, 1]: (L + 1, 3) float64."""
    t = np.linspace(0.0, 1.0, level + 1)  # (L + 1,)
    return np.stack([(1 - t) ** 2, 2 * t * (1 - t), t**2], axis=1)


def tessellate_patches(
    control: np.ndarray, control_normals: np.ndarray, level: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sample every patch on a (level + 1)² grid and split each grid cell into two triangles.

    Returns (vertices (Vp, 3), normals (Vp, 3), triangles (Tp, 3) int64 into vertices, patch id (Tp,)).
    Vertices of patch p occupy rows p·(L+1)² … (p+1)·(L+1)² − 1, row-major over (v, u).
    """
    if level < 1:
        raise IngestError(f"patch level must be >= 1, got {level}")
    weights = bernstein(level)  # (L + 1, 3)
    n = level + 1
    points = np.einsum("vi,uj,pijc->pvuc", weights, weights, control).reshape(-1, 3)  # (P·n², 3)
    shading = np.einsum("vi,uj,pijc->pvuc", weights, weights, control_normals).reshape(-1, 3)  # (P·n², 3)
    v, u = np.meshgrid(np.arange(level), np.arange(level), indexing="ij")  # (L, L) each
    corner = (v * n + u).ravel()  # (L²,) top-left corner of each cell
    cell = np.stack([corner, corner + n, corner + 1, corner + 1, corner + n, corner + n + 1], axis=1).reshape(
        -1, 3
    )  # (2L², 3) one patch's triangles
    patch_count = len(control)
    tris = (np.arange(patch_count)[:, None, None] * n * n + cell[None]).reshape(-1, 3)  # (P·2L², 3)
    owner = np.repeat(np.arange(patch_count), len(cell))  # (Tp,)
    return points, shading, tris.astype(np.int64), owner
