"""Barrier surfaces (a Quake 3 sky, the lid of an open procedural scene) are measured like drawn ones:
the field reaches zero there instead of jumping from +u to -u (u the distance to drawn geometry), so
it stays 1-Lipschitz across them, sphere tracing cannot step over a barrier, and physics can certify
moves next to it."""

from __future__ import annotations

import numpy as np

from navi_compiler.compile import compile_scene
from navi_compiler.gmdag import dense_lattice
from navi_compiler.ingest.procedural import generate_scene


def test_open_scene_field_reaches_zero_at_its_lid() -> None:
    scene = generate_scene("yard", 4)
    lid = scene.vertices[scene.barrier_faces.ravel()]  # (3 Fb, 3) meters
    assert len(lid) > 0 and np.ptp(lid[:, 2]) < 1e-9  # a flat, horizontal barrier
    g, _ = compile_scene(scene, resolution=64)
    d = dense_lattice(g)  # (65, 65, 65) voxels
    origin, h = np.array(g.origin), g.voxel_size
    lo = np.ceil((lid[:, :2].min(axis=0) - origin[:2]) / h).astype(int) + 2  # (2,) inside the lid's footprint
    hi = np.floor((lid[:, :2].max(axis=0) - origin[:2]) / h).astype(int) - 2  # (2,)
    z = int(np.round((lid[0, 2] - origin[2]) / h))  # the lattice plane nearest the lid
    plane = d[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, z]  # (X, Y) voxels
    assert plane.size > 100
    assert float(np.abs(plane).max()) <= 0.5 + g.quant_step  # within half a voxel of the barrier
    # along z (the lid's normal) neighbours differ by at most one voxel (+ quantisation) wherever both
    # are brick samples: no +u / -u jump anywhere
    a, b = d[:, :, :-1], d[:, :, 1:]
    both = (np.abs(a) < 4.0) & (np.abs(b) < 4.0)
    assert float(np.abs(a - b)[both].max()) <= 1.0 + 2 * g.quant_step
