"""The .gmdag file: reader, writer and validator (docs/GMDAG.md, format versions 1 and 2).

Version 2 (what `encode_gmdag` writes) stores the octree payload (nodes, bricks, brick classes) as
one zlib stream; version 1 stores it raw and stays readable. Both decode to the same `Gmdag`.

`decode_gmdag` never trusts its input: every size is checked against the byte count before an
array is made, the zlib stream is inflated with a hard output limit, every check is vectorised, and
every failure is one `GmdagError` with a clear message. `encode_gmdag` runs the same validation, so
an invalid `Gmdag` is never written.
"""

from __future__ import annotations

import math
import os
import struct
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = b"GMDAG\x00\r\n"
VERSION = 2  # what encode_gmdag writes
VERSIONS = (1, 2)  # what decode_gmdag reads: 1 raw payload, 2 zlib-compressed payload
ZLIB_LEVEL = 6  # compression level of the payload stream (zlib's default: ~8x on bricks, ~15 ms/MB)
MAX_INFLATE_RATIO = 1032  # deflate cannot expand a stream by more than this (RFC 1951 bound, rounded up)
HEADER_BYTES = 128
BRICK_CELLS = 8  # B: cells per brick edge
BRICK_SIDE = BRICK_CELLS + 1  # 9 samples per brick edge
BRICK_SAMPLES = BRICK_SIDE**3  # 729
MIN_RESOLUTION = 8
MAX_RESOLUTION = 4096
MAX_CLASSES = 256  # class ids are u8
FLAG_INSIDE_SEEDS = 1  # bit 0: sign seeded from inside points
FLAG_LEAK_FALLBACK = 2  # bit 1: the fill leaked; the compiler fell back to outside seeding
KNOWN_FLAGS = FLAG_INSIDE_SEEDS | FLAG_LEAK_FALLBACK

TAG_NODE = 0
TAG_BRICK = 1
TAG_FAR_FREE = 2
TAG_FAR_SOLID = 3
PAYLOAD_MASK = (1 << 30) - 1
FAR_UNITS = 16  # far-code payloads count 1/16 voxel

# magic, version, header_bytes, resolution, brick_cells, levels, root, origin(3), voxel_size, band,
# quant_step, node_count, brick_count, spawn_count, class_count, bounds_min(3), bounds_max(3), flags,
# payload_bytes (version 2; zero in version 1), reserved
_HEADER = struct.Struct("<8s6I3dd2f4I3f3fII8s")
assert _HEADER.size == HEADER_BYTES


class GmdagError(ValueError):
    """A .gmdag file (or an in-memory Gmdag) breaks the format; the message says how."""


@dataclass(frozen=True, eq=False)
class Gmdag:
    """One decoded .gmdag file. Arrays are read-only views when decoded from bytes."""

    resolution: int  # R, cells per cube edge (power of two in [8, 4096])
    levels: int  # L = log2(R / 8), levels of internal nodes
    root: int  # child word (u32) of the root
    origin: tuple[float, float, float]  # min corner of the cube, meters
    voxel_size: float  # h, cell edge, meters
    band: float  # samples are clamped to [-band, band] voxels
    quant_step: float  # voxels per i8 unit (float32(band / 127))
    nodes: np.ndarray  # (node_count, 8) uint32 child words
    bricks: np.ndarray  # (brick_count, 729) int8, sample (i, j, k) at i + 9*j + 81*k
    brick_class: np.ndarray  # (brick_count,) uint8 semantic class id per brick
    spawns: np.ndarray  # (S, 3) float32 known-free points, meters
    class_names: tuple[str, ...]  # class id -> name
    bounds_min: tuple[float, float, float]  # source geometry box, meters (float32 values)
    bounds_max: tuple[float, float, float]
    flags: int  # FLAG_INSIDE_SEEDS | FLAG_LEAK_FALLBACK

    @property
    def cube_max(self) -> tuple[float, float, float]:
        """Max corner of the cube, meters."""
        side = self.resolution * self.voxel_size
        return (self.origin[0] + side, self.origin[1] + side, self.origin[2] + side)


def make_child(tag: int, payload: int) -> int:
    """Pack a child word from its 2-bit tag and 30-bit payload."""
    if not 0 <= tag <= 3 or not 0 <= payload <= PAYLOAD_MASK:
        raise ValueError(f"child word out of range: tag {tag}, payload {payload}")
    return (tag << 30) | payload


def child_tag(word: int) -> int:
    """The tag (bits 31-30) of a child word."""
    return (word >> 30) & 3


def child_payload(word: int) -> int:
    """The payload (bits 29-0) of a child word."""
    return word & PAYLOAD_MASK


def quant_step_for(band: float) -> float:
    """The quant_step a file with this band must carry: float32(band / 127)."""
    return float(np.float32(float(np.float32(band)) / 127.0))


def _fail(msg: str) -> GmdagError:
    return GmdagError(msg)


def _check_placement(g: Gmdag) -> None:
    r = g.resolution
    if not (MIN_RESOLUTION <= r <= MAX_RESOLUTION) or r & (r - 1):
        raise _fail(f"resolution {r} is not a power of two in [{MIN_RESOLUTION}, {MAX_RESOLUTION}]")
    expected_levels = int(math.log2(r // BRICK_CELLS))
    if g.levels != expected_levels:
        raise _fail(f"levels {g.levels} != log2(resolution / 8) = {expected_levels}")
    if not all(math.isfinite(v) for v in g.origin):
        raise _fail(f"origin {g.origin} is not finite")
    if not (math.isfinite(g.voxel_size) and g.voxel_size > 0):
        raise _fail(f"voxel_size {g.voxel_size} is not finite and positive")
    if not all(math.isfinite(v) for v in g.cube_max):
        raise _fail("the cube's max corner (origin + resolution * voxel_size) is not finite")
    if not (math.isfinite(g.band) and g.band > 0 and float(np.float32(g.band)) == g.band):
        raise _fail(f"band {g.band} is not a finite, positive float32")
    if g.quant_step != quant_step_for(g.band):
        raise _fail(f"quant_step {g.quant_step} != float32(band / 127) = {quant_step_for(g.band)}")
    if g.flags & ~KNOWN_FLAGS or g.flags < 0:
        raise _fail(f"unknown flag bits in flags {g.flags:#x}")


def _check_bounds(g: Gmdag) -> None:
    lo = np.array(g.bounds_min, np.float64)  # (3,)
    hi = np.array(g.bounds_max, np.float64)  # (3,)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise _fail(f"bounds {g.bounds_min}..{g.bounds_max} are not finite")
    if (lo > hi).any():
        raise _fail(f"bounds are inverted: min {g.bounds_min} > max {g.bounds_max}")
    cube_lo = np.array(g.origin, np.float64)  # (3,)
    cube_hi = np.array(g.cube_max, np.float64)  # (3,)
    if (lo < cube_lo).any() or (hi > cube_hi).any():
        raise _fail(f"bounds {g.bounds_min}..{g.bounds_max} are not inside the cube {g.origin}..{g.cube_max}")


def _check_arrays(g: Gmdag) -> None:
    n_nodes, n_bricks = len(g.nodes), len(g.bricks)
    if g.nodes.dtype != np.uint32 or g.nodes.ndim != 2 or g.nodes.shape[1] != 8:
        raise _fail(f"nodes must be (node_count, 8) uint32, got {g.nodes.shape} {g.nodes.dtype}")
    if g.bricks.dtype != np.int8 or g.bricks.ndim != 2 or g.bricks.shape[1] != BRICK_SAMPLES:
        raise _fail(f"bricks must be (brick_count, 729) int8, got {g.bricks.shape} {g.bricks.dtype}")
    if g.brick_class.dtype != np.uint8 or g.brick_class.shape != (n_bricks,):
        raise _fail(
            f"brick_class must be ({n_bricks},) uint8, got {g.brick_class.shape} {g.brick_class.dtype}"
        )
    if g.spawns.dtype != np.float32 or g.spawns.ndim != 2 or g.spawns.shape[1] != 3:
        raise _fail(f"spawns must be (S, 3) float32, got {g.spawns.shape} {g.spawns.dtype}")
    if not 0 <= g.root <= 0xFFFFFFFF:
        raise _fail(f"root {g.root} is not a u32 child word")
    if n_nodes > PAYLOAD_MASK + 1 or n_bricks > PAYLOAD_MASK + 1:
        raise _fail("more nodes or bricks than a child word can address")
    if len(g.class_names) > MAX_CLASSES:
        raise _fail(f"class_count {len(g.class_names)} > {MAX_CLASSES} (class ids are u8)")
    if n_bricks and int(g.brick_class.max()) >= len(g.class_names):
        raise _fail(f"brick class id {int(g.brick_class.max())} >= class_count {len(g.class_names)}")
    for name in g.class_names:
        if len(name.encode("utf-8")) > 255:
            raise _fail(f"class name {name[:20]!r}... is longer than 255 UTF-8 bytes")
    if len(g.spawns):
        if not np.isfinite(g.spawns).all():
            raise _fail("spawns hold non-finite coordinates")
        s = g.spawns.astype(np.float64)  # (S, 3) float64
        if (s < np.array(g.origin)).any() or (s > np.array(g.cube_max)).any():
            raise _fail("a spawn lies outside the cube")


def _check_structure(g: Gmdag) -> None:
    """Walk the DAG one depth at a time (vectorised): tags per depth, ranges, order, reachability."""
    nodes = g.nodes.astype(np.int64)  # (node_count, 8) int64
    n_nodes, n_bricks = len(nodes), len(g.bricks)
    depth = np.full(n_nodes, -1, np.int64)  # (node_count,) depth of each node, -1 = not reached
    words = np.array([g.root], np.int64)  # (M,) child words at the current depth
    parents = np.array([-1], np.int64)  # (M,) index of the node holding each word (-1: root)
    for d in range(g.levels + 1):
        tags = words >> 30  # (M,)
        payload = words & PAYLOAD_MASK  # (M,)
        is_node = tags == TAG_NODE  # (M,)
        is_brick = tags == TAG_BRICK  # (M,)
        if d < g.levels and is_brick.any():
            raise _fail(f"a brick at depth {d}; bricks are allowed only at depth {g.levels}")
        if d == g.levels and is_node.any():
            raise _fail(f"an internal node at the brick depth {d}")
        if is_brick.any() and int(payload[is_brick].max()) >= n_bricks:
            raise _fail(f"brick index {int(payload[is_brick].max())} out of range (brick_count {n_bricks})")
        if not is_node.any():
            break
        idx = payload[is_node]  # (K,)
        if int(idx.max()) >= n_nodes:
            raise _fail(f"node index {int(idx.max())} out of range (node_count {n_nodes})")
        if (idx <= parents[is_node]).any():
            raise _fail(
                "a child node index is not larger than its parent's (nodes must be topologically numbered)"
            )
        reached = np.unique(idx)  # (U,)
        if (depth[reached] >= 0).any():
            raise _fail("a node is reached at two depths")
        depth[reached] = d
        words = nodes[reached].ravel()  # (8U,)
        parents = np.repeat(reached, 8)  # (8U,)
    if (depth < 0).any():
        raise _fail(f"node {int(np.argmax(depth < 0))} is not reachable from the root")


def validate_gmdag(g: Gmdag) -> None:
    """Raise GmdagError unless `g` satisfies every rule of docs/GMDAG.md."""
    _check_placement(g)
    _check_bounds(g)
    _check_arrays(g)
    _check_structure(g)


def _names_bytes(names: tuple[str, ...]) -> bytes:
    out = bytearray()
    for name in names:
        raw = name.encode("utf-8")
        out.append(len(raw))
        out += raw
    return bytes(out)


def _payload(g: Gmdag) -> bytes:
    """The octree payload: nodes | bricks | brick_class, raw (what version 2 compresses)."""
    return b"".join(
        [
            np.ascontiguousarray(g.nodes, "<u4").tobytes(),
            np.ascontiguousarray(g.bricks, np.int8).tobytes(),
            np.ascontiguousarray(g.brick_class, np.uint8).tobytes(),
        ]
    )


def payload_bytes(node_count: int, brick_count: int) -> int:
    """Size of the raw octree payload (also what a version 2 stream inflates to)."""
    return node_count * 32 + brick_count * (BRICK_SAMPLES + 1)


def encode_gmdag(g: Gmdag, version: int = VERSION) -> bytes:
    """Serialise a valid Gmdag to bytes (raises GmdagError if it is not valid). `version` 2 (default)
    compresses the octree payload with zlib; 1 writes the older raw layout."""
    if version not in VERSIONS:
        raise ValueError(f"version must be one of {VERSIONS}, got {version}")
    validate_gmdag(g)
    payload = _payload(g)
    if version == 2:
        payload = zlib.compress(payload, ZLIB_LEVEL)
    header = _HEADER.pack(
        MAGIC,
        version,
        HEADER_BYTES,
        g.resolution,
        BRICK_CELLS,
        g.levels,
        g.root,
        *g.origin,
        g.voxel_size,
        g.band,
        g.quant_step,
        len(g.nodes),
        len(g.bricks),
        len(g.spawns),
        len(g.class_names),
        *g.bounds_min,
        *g.bounds_max,
        g.flags,
        len(payload) if version == 2 else 0,
        bytes(8),
    )
    body = b"".join(
        [
            header,
            payload,
            np.ascontiguousarray(g.spawns, "<f4").tobytes(),
            _names_bytes(g.class_names),
        ]
    )
    return body + struct.pack("<I", zlib.crc32(body))


def _parse_names(data: bytes, start: int, end: int, count: int) -> tuple[str, ...]:
    names: list[str] = []
    pos = start
    for _ in range(count):
        if pos >= end:
            raise _fail("truncated: the class names run past the end of the file")
        length = data[pos]
        if pos + 1 + length > end:
            raise _fail("truncated: a class name runs past the end of the file")
        try:
            names.append(data[pos + 1 : pos + 1 + length].decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise _fail(f"class name {len(names)} is not UTF-8") from exc
        pos += 1 + length
    if pos != end:
        raise _fail(f"{end - pos} trailing bytes after the class names")
    return tuple(names)


def _inflate(stream: memoryview, expected: int) -> bytes:
    """Inflate a version 2 payload stream that must hold exactly `expected` bytes (never more are made)."""
    if expected > MAX_INFLATE_RATIO * len(stream):
        raise _fail(
            f"the counts need a {expected}-byte payload, more than a {len(stream)}-byte zlib stream can hold"
        )
    inflater = zlib.decompressobj()
    try:
        out = inflater.decompress(stream, expected)
    except zlib.error as exc:
        raise _fail(f"the compressed payload is corrupt ({exc})") from exc
    if inflater.unconsumed_tail:
        raise _fail(f"the compressed payload holds more than the {expected} bytes the counts say")
    if not inflater.eof or len(out) != expected:
        raise _fail(f"the compressed payload holds {len(out)} bytes or ends early; the counts say {expected}")
    if inflater.unused_data:
        raise _fail(f"{len(inflater.unused_data)} stray bytes after the compressed payload")
    return out


def decode_gmdag(data: bytes) -> Gmdag:
    """Parse and fully validate a .gmdag byte string (version 1 or 2); any defect raises GmdagError."""
    data = bytes(data)
    if len(data) < HEADER_BYTES + 4:
        raise _fail(f"truncated: {len(data)} bytes; a .gmdag file has at least {HEADER_BYTES + 4}")
    fields = _HEADER.unpack_from(data, 0)
    magic, version, header_bytes, resolution, brick_cells, levels, root = fields[:7]
    origin = (float(fields[7]), float(fields[8]), float(fields[9]))
    voxel_size, band, quant_step = float(fields[10]), float(fields[11]), float(fields[12])
    node_count, brick_count, spawn_count, class_count = fields[13:17]
    bounds_min = (float(fields[17]), float(fields[18]), float(fields[19]))
    bounds_max = (float(fields[20]), float(fields[21]), float(fields[22]))
    flags, packed_bytes, reserved = fields[23], fields[24], fields[25]
    if magic != MAGIC:
        raise _fail(f"bad magic {magic!r}; not a .gmdag file")
    if version not in VERSIONS:
        raise _fail(
            f"unsupported format version {version} (this reader knows {', '.join(map(str, VERSIONS))})"
        )
    if header_bytes != HEADER_BYTES:
        raise _fail(f"header_bytes {header_bytes} != {HEADER_BYTES}")
    (stored_crc,) = struct.unpack_from("<I", data, len(data) - 4)
    if zlib.crc32(data[:-4]) != stored_crc:
        raise _fail("checksum mismatch: the file is corrupt or truncated")
    if brick_cells != BRICK_CELLS:
        raise _fail(f"brick_cells {brick_cells} != {BRICK_CELLS}")
    if reserved != bytes(8) or (version == 1 and packed_bytes != 0):
        raise _fail("reserved header bytes are not zero")
    if class_count > MAX_CLASSES:
        raise _fail(f"class_count {class_count} > {MAX_CLASSES} (class ids are u8)")
    raw_bytes = payload_bytes(node_count, brick_count)
    stored = raw_bytes if version == 1 else packed_bytes  # bytes of the payload section in the file
    off_spawns = HEADER_BYTES + stored
    off_names = off_spawns + spawn_count * 12
    end = len(data) - 4
    if off_names + class_count > end:
        raise _fail(
            f"truncated: counts (nodes {node_count}, bricks {brick_count}, spawns {spawn_count}, "
            f"classes {class_count}, payload {stored} bytes) need more than the file's {len(data)} bytes"
        )
    names = _parse_names(data, off_names, end, class_count)
    buf = memoryview(data)
    payload = (
        buf[HEADER_BYTES:off_spawns]
        if version == 1
        else memoryview(_inflate(buf[HEADER_BYTES:off_spawns], raw_bytes))
    )
    off_bricks = node_count * 32
    off_class = off_bricks + brick_count * BRICK_SAMPLES
    g = Gmdag(
        resolution=resolution,
        levels=levels,
        root=root,
        origin=origin,
        voxel_size=voxel_size,
        band=band,
        quant_step=quant_step,
        nodes=np.frombuffer(payload[:off_bricks], "<u4").reshape(node_count, 8).astype(np.uint32),
        bricks=np.frombuffer(payload[off_bricks:off_class], np.int8).reshape(brick_count, BRICK_SAMPLES),
        brick_class=np.frombuffer(payload[off_class:], np.uint8),
        spawns=np.frombuffer(buf[off_spawns:off_names], "<f4").reshape(spawn_count, 3).astype(np.float32),
        class_names=names,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        flags=flags,
    )
    validate_gmdag(g)
    return g


def read_gmdag(path: str | os.PathLike[str]) -> Gmdag:
    """Read and validate a .gmdag file."""
    return decode_gmdag(Path(path).read_bytes())


def write_gmdag(g: Gmdag, path: str | os.PathLike[str]) -> None:
    """Write atomically: a temp file in the same folder, fsync, then os.replace."""
    data = encode_gmdag(g)
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        os.fchmod(fd, 0o644)  # mkstemp makes 0600; a scene/model file is meant to be shared
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def leaf_cubes(g: Gmdag) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every leaf (brick or far code) of the octree: (words (M,) uint32, depth (M,) int64, min corner
    (M, 3) int64 in cells). Vectorised descent, one depth at a time."""
    words = np.array([g.root], np.int64)  # (M,) child words at the current depth
    corners = np.zeros((1, 3), np.int64)  # (M, 3) cell coordinates of each word's cube
    offsets = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)  # (8, 3)
    leaf_words, leaf_depth, leaf_corner = [], [], []
    for d in range(g.levels + 1):
        is_node = (words >> 30) == TAG_NODE  # (M,)
        leaf_words.append(words[~is_node])
        leaf_depth.append(np.full(int((~is_node).sum()), d, np.int64))
        leaf_corner.append(corners[~is_node])
        if not is_node.any():
            break
        half = g.resolution >> (d + 1)
        idx = words[is_node] & PAYLOAD_MASK  # (K,)
        words = g.nodes[idx].astype(np.int64).ravel()  # (8K,)
        corners = (corners[is_node][:, None, :] + half * offsets[None]).reshape(-1, 3)  # (8K, 3)
    return (
        np.concatenate(leaf_words).astype(np.uint32),
        np.concatenate(leaf_depth),
        np.concatenate(leaf_corner),
    )


def dense_lattice(g: Gmdag) -> np.ndarray:
    """Decode the whole field to ((R+1), (R+1), (R+1)) float32 voxels, indexed [x, y, z].

    Far codes decode to their signed lower bound (+payload/16 free, -payload/16 solid); they are
    written first, then bricks, so on a face shared by a brick and a far cube the brick sample wins.
    """
    n = g.resolution + 1
    out = np.zeros((n, n, n), np.float32)  # (R+1, R+1, R+1) float32
    words, depth, corner = leaf_cubes(g)
    tags = words >> 30  # (M,)
    far = tags >= TAG_FAR_FREE  # (M,)
    for w, d, c in zip(words[far], depth[far], corner[far], strict=True):
        side = g.resolution >> int(d)
        value = np.float32((int(w) & PAYLOAD_MASK) / FAR_UNITS)
        sign = np.float32(1.0 if (int(w) >> 30) == TAG_FAR_FREE else -1.0)
        out[c[0] : c[0] + side + 1, c[1] : c[1] + side + 1, c[2] : c[2] + side + 1] = sign * value
    step = np.float32(g.quant_step)
    for w, c in zip(words[tags == TAG_BRICK], corner[tags == TAG_BRICK], strict=True):
        brick = g.bricks[int(w) & PAYLOAD_MASK].reshape(BRICK_SIDE, BRICK_SIDE, BRICK_SIDE)  # (k, j, i) int8
        out[c[0] : c[0] + BRICK_SIDE, c[1] : c[1] + BRICK_SIDE, c[2] : c[2] + BRICK_SIDE] = (
            brick.transpose(2, 1, 0).astype(np.float32) * step
        )
    return out
