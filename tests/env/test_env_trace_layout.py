"""The runtime layout built by scene.py (runtime tree, leaf grid, corner-word bricks, brick atlas) holds
exactly the file's data but for the all-solid bricks (far-solid codes), and the tracer gives the same
results whatever the grid depth (the node descent below the grid)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import navi_env.tracer.scene as scene_mod
from navi_compiler.gmdag import PAYLOAD_MASK, TAG_BRICK, TAG_FAR_FREE, TAG_FAR_SOLID, TAG_NODE, Gmdag
from navi_env.tracer.analytic_scenes import (
    AnalyticScene,
    Box,
    demo_room,
    free_points,
    leaf_kind_scenes,
    random_directions,
)
from navi_env.tracer.scene import (
    BRICK_WORDS,
    atlas_shift,
    brick_atlas,
    corner_words,
    grid_depth,
    leaf_grid,
    load_corpus,
    load_scene,
    runtime_tree,
    scene_nbytes,
)
from navi_env.tracer.trace import sample_distance, trace
from navi_env.tracer.trace_ref import brick_samples, trace_ref


def _solid_block() -> AnalyticScene:
    """A box whose faces lie 1.6 voxels outside the brick [16, 24)^3: that brick is all solid yet
    within the band, so the file holds it and the runtime tree makes it far solid."""
    return AnalyticScene((Box((3.6, 3.6, 3.6), (9.0, 9.0, 9.0)),), resolution=32, voxel_size=0.25)


def test_corner_words_hold_every_sample_plus_128() -> None:
    rng = np.random.default_rng(0)
    bricks = rng.integers(-128, 128, size=(5, 729)).astype(np.int8)  # (Nb, 729) every i8 value range
    bricks[0] = np.arange(729) % 256 - 128  # (729,) each position distinct
    words = corner_words(bricks)  # (Nb, 576) uint32
    assert words.shape == (5, BRICK_WORDS) and words.dtype == np.uint32
    s = bricks.astype(np.int64).reshape(5, 9, 9, 9)  # (Nb, k, j, i)
    for i, j, k in [(0, 0, 0), (7, 7, 8), (3, 5, 2), (7, 0, 4), (0, 7, 8)]:
        w = words[:, (8 * i + j) * 9 + k].astype(np.int64)  # (Nb,)
        for byte, (di, dj) in enumerate([(0, 0), (1, 0), (0, 1), (1, 1)]):
            assert np.array_equal((w >> (8 * byte)) & 0xFF, s[:, k, j + dj, i + di] + 128)
    back = brick_samples(torch.from_numpy(words.reshape(-1).view(np.int32)))  # (Nb * 729,) int8
    assert torch.equal(back, torch.from_numpy(bricks.reshape(-1)))


def _descend(g: Gmdag | scene_mod.RuntimeTree, cell: tuple[int, int, int]) -> tuple[int, int, int]:
    """(tag, payload, log2 edge) of the leaf holding a cell, from the root, one level at a time."""
    word, shift = g.root, g.levels + 3
    nodes = g.nodes.reshape(-1, 8)
    while word >> 30 == TAG_NODE and shift > 3:
        shift -= 1
        child = sum(((cell[a] >> shift) & 1) << a for a in range(3))
        word = int(nodes[word & PAYLOAD_MASK, child])
    return word >> 30, word & PAYLOAD_MASK, shift


@pytest.mark.parametrize("depth_cap", [7, 2, 0])
def test_leaf_grid_entries_are_the_descent_from_the_root(
    monkeypatch: pytest.MonkeyPatch, depth_cap: int
) -> None:
    monkeypatch.setattr(scene_mod, "MAX_GRID_DEPTH", depth_cap)
    rng = np.random.default_rng(1)
    for s in leaf_kind_scenes():
        g = s.gmdag()
        d = grid_depth(g.levels)
        entries = leaf_grid(g).astype(np.int64)  # (8^D,)
        assert d == min(g.levels, depth_cap) and len(entries) == 8**d
        gshift = g.levels + 3 - d
        for cell in rng.integers(0, g.resolution, size=(300, 3)):
            gx, gy, gz = (int(c) >> gshift for c in cell)
            e = int(entries[(gz << (2 * d)) | (gy << d) | gx])
            tag, payload, shift = _descend(g, tuple(int(c) for c in cell))
            if shift >= gshift:  # the leaf lies at or above the grid depth: the entry is that leaf
                assert (e >> 30, e & (2**26 - 1), (e >> 26) & 15) == (tag, payload, shift)
            else:  # deeper: the entry is the internal node covering the grid cell
                assert e >> 30 == TAG_NODE and (e >> 26) & 15 == gshift


def test_runtime_tree_turns_every_all_solid_brick_into_a_far_solid_code() -> None:
    """An all-negative brick becomes far solid, its bound the smallest magnitude among its samples (the
    float32 field, floored to 1/16 voxel); every other leaf is the file's, bricks renumbered in order."""
    rng = np.random.default_rng(2)
    solid_seen = kept_seen = 0
    for s in [*leaf_kind_scenes(), _solid_block()]:
        g = s.gmdag()
        g = dataclasses.replace(g, brick_class=(np.arange(len(g.bricks)) % 7).astype(np.uint8))
        t = runtime_tree(g)
        all_solid = (g.bricks < 0).all(axis=1)  # (Nb,)
        assert len(t.bricks) == int((~all_solid).sum()) and t.nodes.shape == (len(g.nodes), 8)
        held = np.flatnonzero(~all_solid)  # (Nb',) file index of each brick held
        assert np.array_equal(t.bricks, g.bricks[held]) and np.array_equal(t.brick_class, g.brick_class[held])
        q = np.float32(g.quant_step)
        for cell in rng.integers(0, g.resolution, size=(400, 3)):
            c = tuple(int(v) for v in cell)
            ftag, fpay, fshift = _descend(g, c)
            tag, payload, shift = _descend(t, c)
            assert shift == fshift
            if ftag != TAG_BRICK:
                assert (tag, payload) == (ftag, fpay)
            elif all_solid[fpay]:
                solid_seen += 1
                bound = np.floor(16.0 * float(np.float32(-int(g.bricks[fpay].max())) * q))
                assert (tag, payload) == (TAG_FAR_SOLID, bound)
            else:
                kept_seen += 1
                assert tag == TAG_BRICK and held[payload] == fpay
    assert solid_seen > 0 and kept_seen > 0


def test_the_field_is_the_files_but_a_bound_in_all_solid_bricks() -> None:
    """sample_distance against the file's own samples: the trilinear field of its brick, or in an
    all-solid brick the (negative) far bound, never deeper than the file's field there."""
    rng = np.random.default_rng(5)
    for s in [*leaf_kind_scenes(), _solid_block()]:
        g = s.gmdag()
        corpus = load_scene(g)
        ids = torch.zeros(2000, dtype=torch.int64)  # (N,)
        world = torch.tensor(
            np.array(g.origin) + rng.uniform(0.0, g.resolution, size=(2000, 3)) * g.voxel_size,
            dtype=torch.float32,
        )  # (N, 3) meters
        got = sample_distance(corpus, ids, world).double().numpy() / g.voxel_size  # (N,) voxels
        pv = (world.double().numpy() - np.array(g.origin, np.float32)) * np.float32(
            1.0 / g.voxel_size
        )  # (N, 3)
        q = float(np.float32(g.quant_step))
        for n in range(len(pv)):
            cell = tuple(int(v) for v in np.clip(np.floor(pv[n]), 0, g.resolution - 1))
            tag, payload, _ = _descend(g, cell)
            if tag != TAG_BRICK:
                assert got[n] == (payload / 16 if tag == TAG_FAR_FREE else -payload / 16)
                continue
            b = g.bricks[payload].reshape(9, 9, 9).astype(np.float64)  # (k, j, i)
            i, j, k = (cell[a] % 8 for a in range(3))
            fx, fy, fz = (float(np.clip(pv[n][a] - cell[a], 0.0, 1.0)) for a in range(3))
            c = b[k : k + 2, j : j + 2, i : i + 2]  # (2, 2, 2) [dz, dy, dx]
            x = c[..., 0] + fx * (c[..., 1] - c[..., 0])
            y = x[:, 0] + fy * (x[:, 1] - x[:, 0])
            field = (y[0] + fz * (y[1] - y[0])) * q  # the file's trilinear field, voxels
            if (b < 0).all():
                assert 0 < -got[n] <= -field + 1e-6 and -got[n] >= -b.max() * q - 1 / 16
            else:
                assert abs(got[n] - field) < 1e-5


def test_rays_hit_the_same_surfaces_without_the_all_solid_bricks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tracing the runtime tree against tracing the file's own tree: rays from free space stop on the
    same surfaces at the same depths (the far-solid bound only enters a crossing's last secant step
    when that step ends in an all-solid brick, and the class of such a hit)."""
    scenes = [*leaf_kind_scenes(), _solid_block()]
    ids = torch.arange(len(scenes)).repeat_interleave(8)  # (B,)
    origins = torch.tensor(
        np.concatenate([free_points(s, 8, 0.0, seed=30 + i) for i, s in enumerate(scenes)]),
        dtype=torch.float32,
    )  # (B, 3)
    dirs = torch.tensor(random_directions(600, seed=31), dtype=torch.float32)  # (R, 3)

    def run() -> tuple[torch.Tensor, torch.Tensor]:
        corpus = load_corpus([s.gmdag() for s in scenes])
        depth = torch.empty(len(ids), 600)  # (B, R) float32
        sem = torch.empty(len(ids), 600, dtype=torch.int32)  # (B, R) int32
        trace(corpus, ids, origins, dirs, out_depth=depth, out_semantic=sem)
        return depth, sem

    held, held_sem = run()
    monkeypatch.setattr(
        scene_mod,
        "runtime_tree",
        lambda g: scene_mod.RuntimeTree(g.root, g.nodes.reshape(-1, 8), g.bricks, g.brick_class, g.levels),
    )
    full, full_sem = run()
    # A difference needs a crossing refined to within a 64th of a step of an all-solid brick's face;
    # here (and on 344k rays of three OpenArena maps, docs/PERFORMANCE.md) there is none.
    assert torch.equal(held, full) and torch.equal(held_sem, full_sem)
    assert float((held_sem > 0).float().mean()) > 0.2


def _trace_both(corpus: scene_mod.SceneCorpus, scenes: list[AnalyticScene]) -> tuple[torch.Tensor, ...]:
    per = 5
    origins = np.concatenate([free_points(s, per, 0.0, seed=i) for i, s in enumerate(scenes)])  # (B, 3)
    ids = torch.arange(len(scenes)).repeat_interleave(per)  # (B,)
    o = torch.tensor(origins, dtype=torch.float32)  # (B, 3)
    dirs = torch.tensor(random_directions(200, seed=3), dtype=torch.float32)  # (R, 3)
    out = []
    for fn in (trace, trace_ref):
        depth = torch.full((len(ids), 200), -1.0)  # (B, R) float32
        sem = torch.full((len(ids), 200), -1, dtype=torch.int32)  # (B, R) int32
        steps = torch.full((len(ids), 200), -1, dtype=torch.int32)  # (B, R) int32
        fn(corpus, ids, o, dirs, out_depth=depth, out_semantic=sem, out_steps=steps)
        out += [depth, sem, steps]
    return tuple(out)


def test_traces_do_not_depend_on_the_grid_depth(monkeypatch: pytest.MonkeyPatch) -> None:
    scenes = leaf_kind_scenes()
    full = _trace_both(load_corpus([s.gmdag() for s in scenes]), scenes)
    monkeypatch.setattr(scene_mod, "MAX_GRID_DEPTH", 1)  # the node descent does the rest
    shallow = _trace_both(load_corpus([s.gmdag() for s in scenes]), scenes)
    for a, b in zip(full, shallow, strict=True):
        assert torch.equal(a, b)
    for a, b in zip(full[:3], full[3:], strict=True):  # compiled == reference, bit for bit
        assert torch.equal(a, b)
    assert float((full[1] > 0).float().mean()) > 0.2


def test_huge_far_payloads_clamp_without_changing_results() -> None:
    g = demo_room(16, 4.0).gmdag()
    far = (TAG_FAR_FREE << 30) | (2**29 + 5)  # a valid, absurdly large lower bound at the root
    empty = dataclasses.replace(
        g, root=far, nodes=np.zeros((0, 8), np.uint32), bricks=np.zeros((0, 729), np.int8),
        brick_class=np.zeros(0, np.uint8),
    )  # fmt: skip
    entries = leaf_grid(empty)  # (8^D,) uint32
    assert (entries >> 30 == TAG_FAR_FREE).all() and (entries & (2**26 - 1) == 2**26 - 1).all()
    corpus = load_scene(empty)
    origins = torch.tensor([[1.0, 2.0, 1.5], [-3.0, 1.0, 1.0]])  # (B, 3) inside and outside the cube
    dirs = torch.tensor(random_directions(30, seed=4), dtype=torch.float32)  # (R, 3)
    got, want = torch.empty(2, 30), torch.empty(2, 30)  # (B, R) float32 each
    trace(corpus, torch.zeros(2, dtype=torch.int64), origins, dirs, out_depth=got, horizon=50.0)
    trace_ref(corpus, torch.zeros(2, dtype=torch.int64), origins, dirs, out_depth=want, horizon=50.0)
    assert torch.equal(got, want) and (got == 50.0).all()


def test_scene_nbytes_counts_every_device_buffer() -> None:
    scenes = leaf_kind_scenes()
    corpus = load_corpus([s.gmdag() for s in scenes])
    total = sum(
        t.numel() * t.element_size() for t in (corpus.nodes, corpus.grid, corpus.bricks, corpus.brick_class)
    )
    total += corpus.table.numel() * corpus.table.element_size()
    assert sum(corpus.nbytes) == total
    for info in corpus.infos:
        assert (
            info.nbytes
            == 32 * info.node_count + 2305 * info.brick_count + 4 * 8 ** grid_depth(info.levels) + 64
        )


def test_too_many_bricks_for_the_grid_payload_is_rejected(monkeypatch: pytest.MonkeyPatch) -> None:
    g = demo_room(32, 8.0).gmdag()
    monkeypatch.setattr(scene_mod, "GRID_PAYLOAD_LIMIT", len(g.bricks))
    with pytest.raises(ValueError, match="at most"):
        load_scene(g)


def test_brick_atlas_holds_every_brick_once_as_a_tile() -> None:
    """Brick b is the 9^3 tile at 9 (b mod 2^p, (b >> p) mod 2^p, b >> 2p), texel (i, j, k) = sample (i, j, k)."""
    assert [atlas_shift(n) for n in (0, 1, 2, 8, 9, 64, 65, 512, 513)] == [0, 0, 1, 1, 2, 2, 3, 3, 4]
    rng = np.random.default_rng(3)
    for n in (0, 1, 5, 70):
        bricks = rng.integers(-127, 128, size=(n, 729), dtype=np.int8)  # (Nb, 729) sample i + 9j + 81k
        texels, p = brick_atlas(bricks)  # (9Z, 9Y, 9X) int8 [z, y, x]
        side, slabs = 1 << p, max(1, -(-n // (1 << 2 * p)))
        assert p == atlas_shift(n) and texels.shape == (9 * slabs, 9 * side, 9 * side)
        used = np.zeros(texels.shape, bool)
        for b in range(n):
            x, y, z = 9 * (b % side), 9 * ((b >> p) % side), 9 * (b >> 2 * p)
            tile = texels[z : z + 9, y : y + 9, x : x + 9]  # (9k, 9j, 9i)
            assert np.array_equal(tile.reshape(-1), bricks[b])  # [k, j, i] flattens to i + 9j + 81k
            used[z : z + 9, y : y + 9, x : x + 9] = True
        assert (texels[~used] == 0).all() and used.sum() == 729 * n


def test_scene_bytes_on_cuda_count_a_729_byte_tile_per_brick() -> None:
    assert scene_nbytes(3, 10, 6, atlas=True) == 32 * 3 + 730 * 10 + 4 * 64**3 + 64
    assert scene_nbytes(3, 10, 6) == 32 * 3 + 2305 * 10 + 4 * 64**3 + 64
