"""Scenes on a device: many .gmdag scenes resident at once, addressed by index.

A `SceneCorpus` packs every scene's child words, leaf grid, bricks and brick classes into one buffer
each, plus a table with one 16-word record per scene (layout `SceneWord` in csrc/scene_record.h).
Payloads stay relative to their scene; the record's offsets rebase them at trace time, so loading is a
few vectorised numpy passes and one host-to-device copy per buffer.

The buffers are a runtime layout of the file's data, built here (the .gmdag format does not change):
- the runtime tree (`runtime_tree`): the file's child words, except that a brick whose 729 samples are
  all negative (inside solid, near a surface: 0.5-73% of the bricks of the OpenArena maps) becomes a
  far-solid code whose bound is its smallest sample magnitude, floored to 1/16 voxel (inside solid
  the tracers use the field only for its sign and a crossing's last secant step), so those bricks are
  not held;
- the leaf grid: the octree descended once, at load, to depth D = min(L, 7); entry (z * 2^D + y) * 2^D + x
  holds the child word there (or the leaf above it) as tag << 30 | log2(cube edge) << 26 | payload,
  so the tracer finds a leaf with one load instead of up to L dependent ones;
- bricks on the CPU: corner words, 576 u32 per brick; word (8i + j) * 9 + k holds the samples
  (i, j, k), (i+1, j, k), (i, j+1, k), (i+1, j+1, k) plus 128 in bytes 0..3, so a trilinear sample is
  two adjacent 32-bit loads instead of eight scattered bytes;
- bricks on a CUDA device: the brick atlas, one 3-d texture of int8 samples holding each brick once
  as a 9 x 9 x 9 tile (729 bytes a brick instead of the corner words' 2,304), which the texture unit
  interpolates trilinearly in one fetch (`BrickAtlas`, `brick_atlas`).

Shapes: S scenes, Nn nodes (all scenes), Nb bricks (all scenes), Ng grid entries (all scenes),
P spawns of one scene.
"""

from __future__ import annotations

import ctypes
import os
import warnings
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from navi_compiler.gmdag import (
    BRICK_SIDE,
    PAYLOAD_MASK,
    TAG_BRICK,
    TAG_FAR_SOLID,
    TAG_NODE,
    Gmdag,
    read_gmdag,
)

SCENE_WORDS = 16  # 32-bit words per scene record
# Word indices of a scene record (mirror of enum SceneWord in csrc/scene_record.h).
W_ROOT, W_NODE_OFFSET, W_BRICK_OFFSET, W_RESOLUTION, W_LEVELS = 0, 1, 2, 3, 4
W_ORIGIN, W_VOXEL, W_INV_VOXEL, W_QUANT, W_BAND = 5, 8, 9, 10, 11
W_GRID_OFFSET, W_GRID_DEPTH = 12, 13
MAX_OFFSET = 2**32 - 1  # node, brick and grid offsets are u32
MAX_GRID_DEPTH = 7  # the leaf grid has at most 128^3 entries (8 MiB) per scene
GRID_SHIFT_BIT = 26  # grid entry: tag << 30 | log2(cube edge) << 26 | payload
GRID_PAYLOAD_LIMIT = 1 << GRID_SHIFT_BIT  # node and brick indices of a scene must stay below
BRICK_WORDS = 8 * 8 * 9  # corner words per runtime brick

SceneSource = str | os.PathLike[str] | Gmdag


@dataclass(frozen=True)
class SceneInfo:
    """Host-side facts about one resident scene (what the environment needs besides the field)."""

    name: str  # file stem, or "scene<i>" for an in-memory Gmdag
    resolution: int  # R, cells per cube edge
    levels: int  # L = log2(R / 8)
    origin: tuple[float, float, float]  # cube min corner, meters
    voxel_size: float  # h, meters
    band: float  # clamp band, voxels
    quant_step: float  # voxels per i8 unit
    bounds_min: tuple[float, float, float]  # source geometry box, meters
    bounds_max: tuple[float, float, float]
    spawns: np.ndarray  # (P, 3) float32 known-free points, meters
    class_names: tuple[str, ...]  # class id -> name
    flags: int  # .gmdag header flags
    node_count: int
    brick_count: int  # bricks held: the file's, less those that became far-solid codes (runtime_tree)
    nbytes: int  # bytes this scene occupies on the device (nodes, grid, bricks, classes, record)

    @property
    def cube_min(self) -> np.ndarray:
        """(3,) float64 min corner of the scene cube, meters."""
        return np.array(self.origin, np.float64)

    @property
    def cube_max(self) -> np.ndarray:
        """(3,) float64 max corner of the scene cube, meters."""
        return self.cube_min + self.resolution * self.voxel_size


@dataclass(frozen=True)
class SceneCorpus:
    """Scenes resident on one device; trace and sample_distance address them by index."""

    nodes: torch.Tensor  # (Nn * 8,) int32 child words (u32 bits), all scenes
    grid: torch.Tensor  # (Ng,) int32 leaf-grid entries (u32 bits), all scenes
    bricks: torch.Tensor  # (Nb * 576,) int32 corner words (u32 bits), all scenes; (0,) on CUDA
    brick_class: torch.Tensor  # (Nb,) uint8 class id per brick, all scenes
    table: torch.Tensor  # (S, 16) int32 scene records
    infos: tuple[SceneInfo, ...]  # (S,) host metadata, same order as the table
    atlas: BrickAtlas | None = None  # the bricks on a CUDA device (None on the CPU)

    @property
    def device(self) -> torch.device:
        return self.table.device

    def __len__(self) -> int:
        return len(self.infos)

    @property
    def nbytes(self) -> list[int]:
        """Device bytes per scene."""
        return [info.nbytes for info in self.infos]

    @property
    def device_bytes(self) -> int:
        """Every byte the corpus holds on its device: the buffers, and the atlas with its padding."""
        buffers = (self.nodes, self.grid, self.bricks, self.brick_class, self.table)
        return sum(t.numel() * t.element_size() for t in buffers) + (
            0 if self.atlas is None else self.atlas.nbytes
        )


class BrickAtlas:
    """The bricks of a CUDA corpus as one 3-d texture (csrc/trace_cuda.cu `navi_atlas_create_cuda`).

    Brick b (corpus index) is the 9 x 9 x 9 texel tile at 9 * (b mod 2^p, (b >> p) mod 2^p, b >> 2p)
    of a (9 * slabs, 9 * 2^p, 9 * 2^p) [z, y, x] array of signed bytes, texel (i, j, k) of the tile
    holding sample (i, j, k). The texture and its array are freed when the atlas is collected.
    """

    def __init__(self, texels: np.ndarray, shift: int, device: torch.device) -> None:
        from navi_env.tracer.cuda_build import cuda_library

        d, h, w = texels.shape
        index = device.index if device.index is not None else torch.cuda.current_device()
        lib = cuda_library()
        _free_pending(lib)
        tex, array = ctypes.c_uint64(0), ctypes.c_void_p(None)
        host = np.ascontiguousarray(texels, np.int8)  # (D, H, W) int8
        code = lib.navi_atlas_create_cuda(
            host.ctypes.data, w, h, d, index, ctypes.byref(tex), ctypes.byref(array)
        )
        if code != 0:
            raise RuntimeError(
                f"could not create the brick atlas ({w} x {h} x {d} texels) on cuda:{index}: "
                f"{lib.navi_cuda_error_string(code).decode()}"
            )
        self.texture = int(tex.value)  # cudaTextureObject_t
        self.shift = shift  # p
        self.shape = (d, h, w)  # texels, [z, y, x]
        self.device = torch.device("cuda", index)
        self.nbytes = d * h * w  # device bytes of the array
        done = weakref.finalize(self, _free_atlas, self.texture, array.value, index)
        done.atexit = False  # the process' exit frees the device memory with the context


_PENDING: list[tuple[int, int | None, int]] = []  # atlases collected while a CUDA graph was capturing


def _free_atlas(texture: int, array: int | None, device: int) -> None:
    """Free a collected atlas now, or at the next atlas creation when a graph capture is under way
    (freeing synchronises the device, which a capture forbids)."""
    from navi_env.tracer.cuda_build import cuda_library

    _PENDING.append((texture, array, device))
    _free_pending(cuda_library())


def _free_pending(lib: ctypes.CDLL) -> None:
    if not _PENDING or torch.cuda.is_current_stream_capturing():
        return
    while _PENDING:
        texture, array, device = _PENDING.pop()
        code = lib.navi_atlas_destroy_cuda(texture, array, device)
        if code != 0:
            warnings.warn(f"freeing a brick atlas on cuda:{device} failed: {lib.navi_cuda_error_string(code).decode()}",
                          RuntimeWarning, stacklevel=2)  # fmt: skip


def atlas_shift(brick_count: int) -> int:
    """p: the smallest with 8^p >= brick_count, so the atlas is at most 2^p tiles along every axis."""
    p = 0
    while 8**p < brick_count:
        p += 1
    return p


def brick_atlas(bricks: np.ndarray) -> tuple[np.ndarray, int]:
    """The atlas texels (9 * slabs, 9 * 2^p, 9 * 2^p) int8 [z, y, x] of bricks (Nb, 729) int8 (sample
    (i, j, k) at i + 9j + 81k) and p; slabs = ceil(Nb / 4^p) (at least one tile, zero-filled)."""
    p = atlas_shift(len(bricks))
    side = 1 << p
    slabs = max(1, -(-len(bricks) // (side * side)))
    tiles = np.zeros((slabs * side * side, BRICK_SIDE**3), np.int8)  # (slots, 729)
    tiles[: len(bricks)] = bricks
    t = tiles.reshape(slabs, side, side, BRICK_SIDE, BRICK_SIDE, BRICK_SIDE)  # (tz, ty, tx, k, j, i)
    t = t.transpose(0, 3, 1, 4, 2, 5)  # (tz, k, ty, j, tx, i)
    return np.ascontiguousarray(t.reshape(slabs * BRICK_SIDE, side * BRICK_SIDE, side * BRICK_SIDE)), p


def grid_depth(levels: int) -> int:
    """D: the leaf grid of a scene with L levels has 2^D cells per axis."""
    return min(levels, MAX_GRID_DEPTH)


def scene_nbytes(node_count: int, brick_count: int, levels: int, atlas: bool = False) -> int:
    """Device bytes of one scene: 32 per node, per brick 4 * 576 corner words (CPU) or a 729-byte
    atlas tile (`atlas`, CUDA) plus a class byte, 4 per leaf-grid entry, one 64-byte record. The atlas'
    padding (fewer than 4^p tiles per corpus) is the corpus', not a scene's (`SceneCorpus.device_bytes`)."""
    per_brick = (BRICK_SIDE**3 if atlas else 4 * BRICK_WORDS) + 1
    return 32 * node_count + per_brick * brick_count + 4 * 8 ** grid_depth(levels) + 4 * SCENE_WORDS


@dataclass(frozen=True)
class RuntimeTree:
    """The child words and bricks a scene is traced from (runtime_tree)."""

    root: int  # child word of the root
    nodes: np.ndarray  # (Nn, 8) uint32 child words
    bricks: np.ndarray  # (Nb, 729) int8 the bricks held, sample (i, j, k) at i + 9j + 81k
    brick_class: np.ndarray  # (Nb,) uint8
    levels: int  # L


def runtime_tree(g: Gmdag) -> RuntimeTree:
    """Scene g's tree as the tracers hold it: a brick whose samples are all negative becomes a far-solid
    code with bound floor(16 * |largest sample| * quant) / 16 voxels (the float32 field the tracers
    would compute there is at least that deep), and the other bricks keep their order, renumbered.

    Inside solid the tracers use the field only for its sign (a sample there ends a ray, which then
    refines the crossing between its last free sample and this one) and the final secant step of that
    refinement, so a ray hits the same surface; the semantic class of such a hit is that of the last
    brick sampled before it instead of the solid brick's.
    """
    count = len(g.bricks)
    top = g.bricks.max(axis=1).astype(np.int16)  # (Nb,) largest sample of each brick
    solid = top < 0  # (Nb,) every sample inside solid
    field = (-top[solid]).astype(np.float32) * np.float32(g.quant_step)  # (K,) float32 voxels
    bound = np.minimum(np.floor(16.0 * field.astype(np.float64)), PAYLOAD_MASK).astype(np.uint32)  # (K,)
    words = np.zeros(count + 1, np.uint32)  # (Nb + 1,) each brick's new child word; the last one unused
    words[:count][solid] = (TAG_FAR_SOLID << 30) | bound
    words[:count][~solid] = (TAG_BRICK << 30) | np.arange(int((~solid).sum()), dtype=np.uint32)

    def rewrite(w: np.ndarray) -> np.ndarray:
        is_brick = (w >> 30) == TAG_BRICK
        return np.where(is_brick, words[np.where(is_brick, w & PAYLOAD_MASK, count)], w).astype(np.uint32)

    return RuntimeTree(
        root=int(rewrite(np.array([g.root], np.uint32))[0]),
        nodes=rewrite(g.nodes.reshape(-1, 8).astype(np.uint32)),  # (Nn, 8)
        bricks=np.ascontiguousarray(g.bricks[~solid]),
        brick_class=np.ascontiguousarray(g.brick_class[~solid]),
        levels=g.levels,
    )


def leaf_grid(g: Gmdag | RuntimeTree) -> np.ndarray:
    """(8^D,) uint32 leaf-grid entries of scene g (its file or runtime tree), D = grid_depth(L), index
    (z * 2^D + y) * 2^D + x.

    Descends the octree from the root one depth at a time (a leaf above depth D fills all its cells):
    entry = tag << 30 | log2(edge of the entry's cube, voxels) << 26 | payload, where an entry still
    holding an internal node (scenes deeper than the grid) has the grid cell's edge. Far payloads
    above 2^26 - 1 are clamped: a smaller lower bound stays a lower bound, and 2^26 / 16 voxels is
    beyond every cube's diagonal, so the tracer's results do not change.
    """
    nodes = g.nodes.reshape(-1, 8)  # (Nn, 8) uint32
    if len(nodes) >= GRID_PAYLOAD_LIMIT or len(g.bricks) >= GRID_PAYLOAD_LIMIT:
        raise ValueError(f"a scene may hold at most {GRID_PAYLOAD_LIMIT - 1} nodes and bricks each")
    words = np.full((1, 1, 1), g.root, np.uint32)  # (n, n, n) child words at the current depth, [z, y, x]
    shifts = np.full((1, 1, 1), g.levels + 3, np.uint32)  # (n, n, n) log2 cube edge of each word
    for _ in range(grid_depth(g.levels)):
        n = words.shape[0]
        inner = (words >> 30) == TAG_NODE  # (n, n, n) internal nodes split into their 8 children
        children = np.repeat(words[..., None], 8, axis=-1)  # (n, n, n, 8) leaves repeat themselves
        if inner.any():
            children[inner] = nodes[words[inner] & PAYLOAD_MASK]
        child_shifts = np.repeat((shifts - inner.astype(np.uint32))[..., None], 8, axis=-1)  # (n, n, n, 8)
        # child c = x | y << 1 | z << 2: (n, n, n, 2z, 2y, 2x) -> (2n, 2n, 2n) in [z, y, x] order
        words = children.reshape(n, n, n, 2, 2, 2).transpose(0, 3, 1, 4, 2, 5).reshape(2 * n, 2 * n, 2 * n)
        shifts = (
            child_shifts.reshape(n, n, n, 2, 2, 2).transpose(0, 3, 1, 4, 2, 5).reshape(2 * n, 2 * n, 2 * n)
        )
    payload = np.minimum(words & PAYLOAD_MASK, GRID_PAYLOAD_LIMIT - 1)  # (n, n, n) only far bounds clamp
    entries = (words >> 30 << 30) | (shifts << GRID_SHIFT_BIT) | payload  # (n, n, n) uint32
    return entries.reshape(-1)


def corner_words(bricks: np.ndarray) -> np.ndarray:
    """(Nb, 576) uint32 corner words of bricks (Nb, 729) int8 (sample (i, j, k) at i + 9j + 81k).

    Word (8i + j) * 9 + k, for i, j in [0, 7] and k in [0, 8], holds the samples (i, j, k),
    (i+1, j, k), (i, j+1, k), (i+1, j+1, k), each plus 128 (a u8), in bytes 0, 1, 2, 3.
    """
    u = (bricks.view(np.uint8) ^ 0x80).reshape(-1, BRICK_SIDE, BRICK_SIDE, BRICK_SIDE)  # (Nb, 9k, 9j, 9i)
    u = u.transpose(0, 3, 2, 1)  # (Nb, 9i, 9j, 9k) uint8 view
    w = np.empty((len(bricks), 8, 8, BRICK_SIDE, 4), np.uint8)  # (Nb, 8i, 8j, 9k, byte)
    w[..., 0], w[..., 1], w[..., 2], w[..., 3] = u[:, :-1, :-1], u[:, 1:, :-1], u[:, :-1, 1:], u[:, 1:, 1:]
    words = w.view("<u4").astype(np.uint32, copy=False)  # (Nb, 8, 8, 9, 1) little-endian words
    return words.reshape(len(bricks), BRICK_WORDS)


def scene_record(g: Gmdag, root: int, node_offset: int, brick_offset: int, grid_offset: int) -> np.ndarray:
    """The (16,) int32 record of scene g, traced from root word `root` (runtime_tree), whose nodes,
    bricks and grid start at the given corpus offsets."""
    words = np.zeros(SCENE_WORDS, np.uint32)  # (16,) uint32
    floats = words.view(np.float32)  # (16,) float32 view of the same words
    words[W_ROOT] = root
    words[W_NODE_OFFSET] = node_offset
    words[W_BRICK_OFFSET] = brick_offset
    words[W_RESOLUTION] = g.resolution
    words[W_LEVELS] = g.levels
    floats[W_ORIGIN : W_ORIGIN + 3] = np.array(g.origin, np.float64).astype(np.float32)
    floats[W_VOXEL] = np.float32(g.voxel_size)
    floats[W_INV_VOXEL] = np.float32(1.0 / g.voxel_size)
    floats[W_QUANT] = np.float32(g.quant_step)
    floats[W_BAND] = np.float32(g.band)
    words[W_GRID_OFFSET] = grid_offset
    words[W_GRID_DEPTH] = grid_depth(g.levels)
    return words.view(np.int32)


def _as_gmdag(src: SceneSource) -> tuple[Gmdag, str | None]:
    if isinstance(src, Gmdag):
        return src, None
    return read_gmdag(src), Path(src).stem


def load_corpus(sources: Sequence[SceneSource], device: str | torch.device = "cpu") -> SceneCorpus:
    """Read (or take) every scene, build its runtime tree, pack them, and copy each buffer to `device`
    once (on a CUDA device the bricks go into the corpus' brick atlas instead of corner words).

    sources: .gmdag paths or in-memory `Gmdag`s (validated by the compiler's reader/builder).
    """
    if len(sources) == 0:
        raise ValueError("load_corpus needs at least one scene")
    dev = torch.device(device)
    on_cuda = dev.type == "cuda"
    trees: list[RuntimeTree] = []
    infos: list[SceneInfo] = []
    records: list[np.ndarray] = []
    grids: list[np.ndarray] = []
    node_offset = brick_offset = grid_offset = 0
    for i, src in enumerate(sources):
        g, stem = _as_gmdag(src)
        t = runtime_tree(g)
        node_count, brick_count = len(t.nodes), len(t.bricks)
        grid = leaf_grid(t)  # (8^D,) uint32
        if (
            node_offset + node_count > MAX_OFFSET
            or (brick_offset + brick_count) * BRICK_WORDS > MAX_OFFSET
            or grid_offset + len(grid) > MAX_OFFSET
        ):
            raise ValueError(
                "the corpus holds more than 2^32 - 1 nodes, brick words or grid entries; split it"
            )
        records.append(scene_record(g, t.root, node_offset, brick_offset, grid_offset))
        grids.append(grid)
        infos.append(
            SceneInfo(
                name=stem if stem is not None else f"scene{i}",
                resolution=g.resolution,
                levels=g.levels,
                origin=g.origin,
                voxel_size=g.voxel_size,
                band=g.band,
                quant_step=g.quant_step,
                bounds_min=g.bounds_min,
                bounds_max=g.bounds_max,
                spawns=np.ascontiguousarray(g.spawns, np.float32),
                class_names=g.class_names,
                flags=g.flags,
                node_count=node_count,
                brick_count=brick_count,
                nbytes=scene_nbytes(node_count, brick_count, g.levels, atlas=on_cuda),
            )
        )
        trees.append(t)
        node_offset += node_count
        brick_offset += brick_count
        grid_offset += len(grid)
    nodes = np.concatenate([t.nodes.reshape(-1) for t in trees]).view(np.int32)  # (Nn * 8,) int32
    grid_all = np.concatenate(grids).view(np.int32)  # (Ng,) int32
    classes = np.concatenate([t.brick_class for t in trees])  # (Nb,) uint8
    table = np.stack(records)  # (S, 16) int32
    atlas = None
    if on_cuda:
        texels, shift = brick_atlas(np.concatenate([t.bricks for t in trees]))  # (9Z, 9Y, 9X) int8
        atlas = BrickAtlas(texels, shift, dev)
        bricks = np.zeros(0, np.int32)  # (0,) the CUDA build reads the atlas
    else:
        bricks = np.concatenate([corner_words(t.bricks).reshape(-1) for t in trees]).view(
            np.int32
        )  # (Nb * 576,)
    return SceneCorpus(
        nodes=torch.from_numpy(nodes).to(dev),
        grid=torch.from_numpy(grid_all).to(dev),
        bricks=torch.from_numpy(bricks).to(dev),
        brick_class=torch.from_numpy(classes).to(dev),
        table=torch.from_numpy(table).to(dev),
        infos=tuple(infos),
        atlas=atlas,
    )


def load_scene(source: SceneSource, device: str | torch.device = "cpu") -> SceneCorpus:
    """One scene on `device`: a corpus of one (scene index 0)."""
    return load_corpus([source], device)
