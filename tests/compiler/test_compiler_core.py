"""Stage-by-stage parity of the C++ core (navi_compiler._core) with the NumPy reference stages."""

from __future__ import annotations

import numpy as np
import pytest

from navi_compiler import _core  # type: ignore[attr-defined]
from navi_compiler.dag.build import build_dag
from navi_compiler.dag.murmur import murmur3_32
from navi_compiler.gmdag import quant_step_for
from navi_compiler.sdf.distance import make_triangles, nearest_triangles, nondegenerate, squared_distances
from navi_compiler.sdf.farfield import NO_SITE, squared_edt


def _random_triangles(rng: np.random.Generator, count: int, r: int) -> np.ndarray:
    centres = rng.uniform(2, r - 2, (count, 1, 3))  # (T, 1, 3)
    return np.ascontiguousarray(centres + rng.normal(0, 2.5, (count, 3, 3)))  # (T, 3, 3) voxels


def test_murmur_twins_agree() -> None:
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 3, 4, 5, 31, 32, 729, 730):
        data = rng.integers(0, 256, n).astype(np.uint8).tobytes()
        assert _core.murmur3_32(data, 0) == murmur3_32(data) and _core.murmur3_32(data, 7) == murmur3_32(
            data, 7
        )


def test_nearest_distances_match_and_are_exact() -> None:
    rng = np.random.default_rng(1)
    corners = _random_triangles(rng, 60, 32)  # (60, 3, 3)
    tri = make_triangles(corners)
    ref = nearest_triangles(tri, 32, 5.0)
    dist, near = _core.nearest(corners, 32, 5.0, 2)
    assert np.array_equal(dist, ref.distance) and np.array_equal(near, ref.triangle)
    # Brute force over every triangle on a sample of lattice points.
    pts = rng.integers(0, 33, (300, 3))  # (P, 3)
    d2 = squared_distances(
        pts[:, None, :].astype(np.float64), tri, np.arange(len(corners))[None, :]
    )  # (P, T)
    exact = np.sqrt(d2.min(axis=1))  # (P,)
    got = dist[pts[:, 0], pts[:, 1], pts[:, 2]]
    within = exact <= 5.0
    assert np.array_equal(got[within], exact[within].astype(np.float32))
    assert np.isinf(got[~within]).all()


def test_nearest_agrees_on_slivers() -> None:
    # The C++ loop prunes candidates by box and plane distance; near-degenerate slivers must not fool it.
    rng = np.random.default_rng(5)
    corners = _random_triangles(rng, 80, 32)  # (80, 3, 3)
    t = rng.uniform(0.2, 0.8, (40, 1))  # (40, 1)
    corners[:40, 2] = corners[:40, 0] + t * (corners[:40, 1] - corners[:40, 0]) + rng.normal(0, 1e-7, (40, 3))
    corners = np.ascontiguousarray(corners[nondegenerate(corners)])
    ref = nearest_triangles(make_triangles(corners), 32, 5.0)
    dist, near = _core.nearest(corners, 32, 5.0, 2)
    assert np.array_equal(dist, ref.distance) and np.array_equal(near, ref.triangle)


def test_squared_edt_matches_brute_force() -> None:
    rng = np.random.default_rng(2)
    sites = rng.random((17, 17, 17)) < 0.01  # (17, 17, 17) bool
    ref = squared_edt(sites)
    got = _core.squared_edt(sites.astype(np.uint8), 2)
    assert np.array_equal(ref, got)
    pts = np.argwhere(np.ones_like(sites))  # (n^3, 3)
    s = np.argwhere(sites)  # (K, 3)
    brute = ((pts[:, None, :] - s[None, :, :]) ** 2).sum(axis=2).min(axis=1).reshape(sites.shape)
    assert np.array_equal(ref, brute)
    assert (_core.squared_edt(np.zeros((9, 9, 9), np.uint8), 1) == NO_SITE).all()


@pytest.mark.parametrize("r", [8, 32, 64])
def test_dag_twins_agree(r: int) -> None:
    x = np.arange(r + 1, dtype=np.float64)
    gx, gy, gz = np.meshgrid(x, x, x, indexing="ij")
    fields = [
        np.sqrt((gx - 0.4 * r) ** 2 + (gy - 0.55 * r) ** 2 + (gz - 0.5 * r) ** 2) - 0.3 * r,
        np.abs(gz - 0.37 * r) - 0.2,  # a thin slab (negative inside)
        np.minimum(gx - 0.5 * r + 0.3, 7.0),  # half space, capped
    ]
    rng = np.random.default_rng(r)
    for field in fields:
        lattice = field.astype(np.float32)
        nb = r // 8
        classes = rng.integers(0, 3, (nb, nb, nb)).astype(np.uint8)
        ref = build_dag(lattice, 4.0, classes)
        root, levels, nodes, bricks, brick_class = _core.build_dag(
            lattice, classes, 4.0, quant_step_for(4.0), 2
        )
        assert (root, levels) == (ref.root, ref.levels)
        assert np.array_equal(nodes, ref.nodes) and np.array_equal(bricks, ref.bricks)
        assert np.array_equal(brick_class, ref.brick_class)
