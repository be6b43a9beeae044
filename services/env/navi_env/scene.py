"""Scenes on a device: many .gmdag scenes resident at once, addressed by index.

A `SceneCorpus` packs every scene's child words, bricks and brick classes into one buffer each, plus
a table with one 16-word record per scene (layout `SceneWord` in csrc/gmdag_trace.h). Child-word
payloads stay relative to their scene; the record's node and brick offsets rebase them at trace time,
so loading is a few numpy concatenations and one host-to-device copy per buffer.

Shapes: S scenes, Nn nodes (all scenes), Nb bricks (all scenes), P spawns of one scene.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from navi_compiler.gmdag import BRICK_SAMPLES, Gmdag, read_gmdag

SCENE_WORDS = 16  # 32-bit words per scene record
# Word indices of a scene record (mirror of enum SceneWord in gmdag_trace.h).
W_ROOT, W_NODE_OFFSET, W_BRICK_OFFSET, W_RESOLUTION, W_LEVELS = 0, 1, 2, 3, 4
W_ORIGIN, W_VOXEL, W_INV_VOXEL, W_QUANT, W_BAND = 5, 8, 9, 10, 11
MAX_OFFSET = 2**32 - 1  # node and brick offsets are u32

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
    brick_count: int
    nbytes: int  # bytes this scene occupies on the device (nodes, bricks, classes, record)

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
    bricks: torch.Tensor  # (Nb * 729,) int8 samples, all scenes
    brick_class: torch.Tensor  # (Nb,) uint8 class id per brick, all scenes
    table: torch.Tensor  # (S, 16) int32 scene records
    infos: tuple[SceneInfo, ...]  # (S,) host metadata, same order as the table

    @property
    def device(self) -> torch.device:
        return self.table.device

    def __len__(self) -> int:
        return len(self.infos)

    @property
    def nbytes(self) -> list[int]:
        """Device bytes per scene."""
        return [info.nbytes for info in self.infos]


def scene_nbytes(node_count: int, brick_count: int) -> int:
    """Device bytes of one scene: 32 per node, 729 + 1 per brick, one 64-byte record."""
    return 32 * node_count + (BRICK_SAMPLES + 1) * brick_count + 4 * SCENE_WORDS


def scene_record(g: Gmdag, node_offset: int, brick_offset: int) -> np.ndarray:
    """The (16,) int32 record of scene g whose nodes and bricks start at the given corpus offsets."""
    words = np.zeros(SCENE_WORDS, np.uint32)  # (16,) uint32
    floats = words.view(np.float32)  # (16,) float32 view of the same words
    words[W_ROOT] = g.root
    words[W_NODE_OFFSET] = node_offset
    words[W_BRICK_OFFSET] = brick_offset
    words[W_RESOLUTION] = g.resolution
    words[W_LEVELS] = g.levels
    floats[W_ORIGIN : W_ORIGIN + 3] = np.array(g.origin, np.float64).astype(np.float32)
    floats[W_VOXEL] = np.float32(g.voxel_size)
    floats[W_INV_VOXEL] = np.float32(1.0 / g.voxel_size)
    floats[W_QUANT] = np.float32(g.quant_step)
    floats[W_BAND] = np.float32(g.band)
    return words.view(np.int32)


def _as_gmdag(src: SceneSource) -> tuple[Gmdag, str | None]:
    if isinstance(src, Gmdag):
        return src, None
    return read_gmdag(src), Path(src).stem


def load_corpus(sources: Sequence[SceneSource], device: str | torch.device = "cpu") -> SceneCorpus:
    """Read (or take) every scene, pack them, and copy each buffer to `device` once.

    sources: .gmdag paths or in-memory `Gmdag`s (validated by the compiler's reader/builder).
    """
    if len(sources) == 0:
        raise ValueError("load_corpus needs at least one scene")
    dev = torch.device(device)
    gmdags: list[Gmdag] = []
    infos: list[SceneInfo] = []
    records: list[np.ndarray] = []
    node_offset = brick_offset = 0
    for i, src in enumerate(sources):
        g, stem = _as_gmdag(src)
        node_count, brick_count = len(g.nodes), len(g.bricks)
        if node_offset + node_count > MAX_OFFSET or brick_offset + brick_count > MAX_OFFSET:
            raise ValueError("the corpus holds more than 2^32 - 1 nodes or bricks; split it")
        records.append(scene_record(g, node_offset, brick_offset))
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
                nbytes=scene_nbytes(node_count, brick_count),
            )
        )
        gmdags.append(g)
        node_offset += node_count
        brick_offset += brick_count
    nodes = np.concatenate([g.nodes.reshape(-1) for g in gmdags]).view(np.int32)  # (Nn * 8,) int32
    bricks = np.concatenate([g.bricks.reshape(-1) for g in gmdags])  # (Nb * 729,) int8
    classes = np.concatenate([g.brick_class for g in gmdags])  # (Nb,) uint8
    table = np.stack(records)  # (S, 16) int32
    return SceneCorpus(
        nodes=torch.from_numpy(nodes).to(dev),
        bricks=torch.from_numpy(bricks).to(dev),
        brick_class=torch.from_numpy(classes).to(dev),
        table=torch.from_numpy(table).to(dev),
        infos=tuple(infos),
    )


def load_scene(source: SceneSource, device: str | torch.device = "cpu") -> SceneCorpus:
    """One scene on `device`: a corpus of one (scene index 0)."""
    return load_corpus([source], device)
