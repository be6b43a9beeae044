"""The DAG stage: quantisation errs toward the surface, far codes are conservative, dedup shares."""

from __future__ import annotations

import numpy as np
import pytest

from navi_compiler.dag.build import build_gmdag, dedup_rows, quantise
from navi_compiler.dag.murmur import murmur3_32, murmur3_32_rows
from navi_compiler.gmdag import (
    FAR_UNITS,
    PAYLOAD_MASK,
    TAG_BRICK,
    TAG_FAR_FREE,
    TAG_FAR_SOLID,
    TAG_NODE,
    dense_lattice,
    encode_gmdag,
    leaf_cubes,
)


def _grid(r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.arange(r + 1, dtype=np.float64)  # (R+1,)
    gx, gy, gz = np.meshgrid(x, x, x, indexing="ij")  # (R+1, R+1, R+1) each
    return gx, gy, gz


def _box_sdf(p: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Exact signed distance to an axis-aligned box, points (..., 3)."""
    q = np.abs(p - centre) - half  # (..., 3)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)  # (...)
    inside = np.minimum(q.max(axis=-1), 0.0)  # (...)
    return outside + inside


def _sphere(r: int, radius: float, c: tuple[float, float, float]) -> np.ndarray:
    gx, gy, gz = _grid(r)
    return (np.sqrt((gx - c[0]) ** 2 + (gy - c[1]) ** 2 + (gz - c[2]) ** 2) - radius).astype(np.float32)


def test_murmur3_matches_published_vectors_and_its_row_twin() -> None:
    assert murmur3_32(b"") == 0
    assert murmur3_32(b"", seed=1) == 0x514E28B7
    assert murmur3_32(b"hello") == 0x248BFA47
    assert murmur3_32(b"The quick brown fox jumps over the lazy dog") == 0x2E4FF723
    rows = np.random.default_rng(0).integers(0, 256, (40, 730)).astype(np.uint8)  # (40, 730)
    for width in (730, 729, 32, 3):
        fast = murmur3_32_rows(np.ascontiguousarray(rows[:, :width]))  # (40,) uint32
        assert [int(h) for h in fast] == [murmur3_32(row[:width].tobytes()) for row in rows]


def test_dedup_rows_agrees_with_exact_uniqueness() -> None:
    rng = np.random.default_rng(1)
    base = rng.integers(0, 256, (7, 33)).astype(np.uint8)  # (7, 33)
    rows = base[rng.integers(0, 7, 200)]  # (200, 33)
    ids, first = dedup_rows(rows)
    assert len(first) == len(np.unique(rows, axis=0))
    assert np.array_equal(rows, rows[first][ids])  # every row maps to an identical representative
    assert (np.diff(first) > 0).all() and first[0] == 0  # ids in order of first appearance


def test_quantise_truncates_toward_zero_and_never_grows() -> None:
    rng = np.random.default_rng(2)
    step = float(np.float32(4.0 / 127))
    d = np.concatenate([rng.uniform(-6, 6, 100_000), np.arange(-130, 131) * step]).astype(np.float32)  # (M,)
    q = quantise(d, step)  # (M,) int8
    decoded = q.astype(np.float32) * np.float32(step)  # (M,) float32
    assert (np.abs(decoded) <= np.abs(d)).all()
    assert (np.sign(q) * np.sign(d) >= 0).all()
    inside = np.abs(d) < 4.0
    assert (np.abs(d - decoded)[inside] < 1.0001 * step).all()
    assert np.abs(q).max() == 127


def test_far_codes_are_conservative_and_signed_on_boxes_and_slabs() -> None:
    r = 64
    gx, gy, gz = _grid(r)
    pts = np.stack([gx, gy, gz], axis=-1)  # (65, 65, 65, 3)
    fields = [
        _box_sdf(pts, np.array([20.3, 31.0, 40.2]), np.array([9.1, 14.7, 5.2])),
        _box_sdf(pts, np.array([32.0, 32.0, 17.4]), np.array([40.0, 40.0, 0.3])),  # thin slab
        _sphere(r, 25.0, (30.0, 36.0, 31.0)),
    ]
    rng = np.random.default_rng(3)
    for exact in fields:
        g = build_gmdag(exact.astype(np.float32), origin=(0, 0, 0), voxel_size=1.0)
        words, depth, corner = leaf_cubes(g)
        far = (words >> 30) >= TAG_FAR_FREE
        assert far.any()
        for w, d, c in zip(words[far], depth[far], corner[far], strict=True):
            side = r >> int(d)
            cube = exact[c[0] : c[0] + side + 1, c[1] : c[1] + side + 1, c[2] : c[2] + side + 1]
            bound = (int(w) & PAYLOAD_MASK) / FAR_UNITS
            sign = 1.0 if int(w) >> 30 == TAG_FAR_FREE else -1.0
            assert (np.sign(cube) == sign).all()
            assert bound <= np.abs(cube).min()
        # Off-lattice points: the trilinear field and the far bounds never claim more than the truth.
        probe = rng.uniform(0, r, (4000, 3))  # (P, 3)
        dense = dense_lattice(g)  # (65, 65, 65)
        i = np.minimum(probe.astype(np.int64), r - 1)  # (P, 3)
        f = probe - i  # (P, 3)
        value = np.zeros(len(probe))  # (P,)
        for c in range(8):
            o = np.array([c & 1, (c >> 1) & 1, (c >> 2) & 1])
            wgt = np.prod(np.where(o == 1, f, 1 - f), axis=1)
            value += wgt * dense[i[:, 0] + o[0], i[:, 1] + o[1], i[:, 2] + o[2]]
        if fields[0] is exact:
            truth = _box_sdf(probe, np.array([20.3, 31.0, 40.2]), np.array([9.1, 14.7, 5.2]))  # (P,)
            far_probe = np.abs(truth) > 5.0
            assert (np.abs(value)[far_probe] <= np.abs(truth)[far_probe] + 1e-6).all()


def test_identical_bricks_and_subtrees_are_shared() -> None:
    r = 128
    gz = _grid(r)[2]
    plane = (gz - 50.5).astype(np.float32)  # (129, 129, 129): every brick along the plane is identical
    g = build_gmdag(plane, origin=(0, 0, 0), voxel_size=1.0)
    assert len(g.bricks) == 2  # the z-rows of bricks holding samples within the band
    assert len(g.nodes) == g.levels + 1  # one distinct node per depth
    # Repeating pattern: a sphere in every 32^3 octant -> the subtree is stored once.
    tile = _sphere(32, 10.0, (16.0, 16.0, 16.0))[:32, :32, :32]  # (32, 32, 32)
    lattice = np.pad(np.tile(tile, (4, 4, 4)), ((0, 1), (0, 1), (0, 1)), mode="wrap")  # (129, 129, 129)
    tiled = build_gmdag(lattice, origin=(0, 0, 0), voxel_size=1.0)
    single = build_gmdag(_sphere(32, 10.0, (16.0, 16.0, 16.0)), origin=(0, 0, 0), voxel_size=1.0)
    assert len(tiled.bricks) == len(single.bricks)
    assert len(tiled.nodes) == len(single.nodes) + 2  # the shared 32^3 subtree plus two tiling levels
    classes = np.zeros((16, 16, 16), np.uint8)  # (16, 16, 16)
    classes[:8] = 1
    split = build_gmdag(
        lattice, origin=(0, 0, 0), voxel_size=1.0, brick_class=classes, class_names=("u", "w")
    )
    assert len(split.bricks) == 2 * len(single.bricks)  # a brick's class is part of its identity


def test_numbering_is_breadth_first_and_deterministic() -> None:
    lattice = _sphere(64, 17.3, (29.1, 35.6, 33.3))
    a = build_gmdag(lattice, origin=(1, 2, 3), voxel_size=0.5)
    b = build_gmdag(lattice.copy(), origin=(1, 2, 3), voxel_size=0.5)
    assert encode_gmdag(a) == encode_gmdag(b)
    tags = a.nodes >> 30  # (N, 8)
    children = (a.nodes & PAYLOAD_MASK)[tags == TAG_NODE]  # (K,)
    first_ref = children[np.sort(np.unique(children, return_index=True)[1])]
    assert np.array_equal(first_ref, np.arange(1, len(a.nodes)))  # first references count up from 1
    bricks = (a.nodes & PAYLOAD_MASK)[tags == TAG_BRICK]
    first_brick = bricks[np.sort(np.unique(bricks, return_index=True)[1])]
    assert np.array_equal(first_brick, np.arange(len(a.bricks)))


def test_far_lower_overrides_the_default_bound() -> None:
    lattice = _sphere(32, 6.0, (8.0, 8.0, 8.0))
    lower = np.full((4, 4, 4), 2.53, np.float32)  # (4, 4, 4)
    g = build_gmdag(lattice, origin=(0, 0, 0), voxel_size=1.0, far_lower=lower)
    words, _, _ = leaf_cubes(g)
    far = words[(words >> 30) >= TAG_FAR_FREE]
    assert len(far) and ((far & PAYLOAD_MASK) == int(np.floor(2.53 * 16))).all()


def test_smallest_cube_and_uniform_fields() -> None:
    free = build_gmdag(np.full((9, 9, 9), 6.0, np.float32), origin=(0, 0, 0), voxel_size=1.0)
    assert free.root >> 30 == TAG_FAR_FREE and (free.root & PAYLOAD_MASK) == int((6.0 - 0.8660254) * 16)
    solid = build_gmdag(np.full((33, 33, 33), -9.0, np.float32), origin=(0, 0, 0), voxel_size=1.0)
    assert solid.root >> 30 == TAG_FAR_SOLID and len(solid.nodes) == 0 and len(solid.bricks) == 0
    one = np.full((9, 9, 9), 6.0, np.float32)
    one[4, 4, 4] = -0.5
    g = build_gmdag(one, origin=(0, 0, 0), voxel_size=1.0)
    assert g.root == TAG_BRICK << 30 and len(g.bricks) == 1
    assert dense_lattice(g)[4, 4, 4] == pytest.approx(-0.5, abs=0.04)
    mixed = np.full((17, 17, 17), 6.0, np.float32)
    mixed[:, :, 9:] = -6.0  # a sign change with no sample inside the band (not a distance field)
    m = build_gmdag(mixed, origin=(0, 0, 0), voxel_size=1.0)
    assert m.root >> 30 == TAG_NODE  # different far tags never merge


def test_bad_lattices_are_refused() -> None:
    with pytest.raises(ValueError, match="power of two"):
        build_gmdag(np.zeros((13, 13, 13), np.float32), origin=(0, 0, 0), voxel_size=1.0)
    with pytest.raises(ValueError, match="float32"):
        build_gmdag(np.zeros((9, 9, 9), np.float64), origin=(0, 0, 0), voxel_size=1.0)
    bad = np.zeros((9, 9, 9), np.float32)
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        build_gmdag(bad, origin=(0, 0, 0), voxel_size=1.0)
