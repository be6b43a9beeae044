"""The .gmdag reader/writer: round trips, the documented layout, and one error per validation rule."""

from __future__ import annotations

import dataclasses
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import (
    FLAG_INSIDE_SEEDS,
    HEADER_BYTES,
    PAYLOAD_MASK,
    TAG_BRICK,
    TAG_FAR_FREE,
    TAG_FAR_SOLID,
    TAG_NODE,
    Gmdag,
    GmdagError,
    child_payload,
    child_tag,
    decode_gmdag,
    dense_lattice,
    encode_gmdag,
    make_child,
    read_gmdag,
    write_gmdag,
)


def _sphere_lattice(r: int, radius: float, centre: tuple[float, float, float]) -> np.ndarray:
    x = np.arange(r + 1, dtype=np.float64)  # (R+1,)
    gx, gy, gz = np.meshgrid(x, x, x, indexing="ij")  # (R+1, R+1, R+1) each
    d = np.sqrt((gx - centre[0]) ** 2 + (gy - centre[1]) ** 2 + (gz - centre[2]) ** 2) - radius
    return d.astype(np.float32)  # (R+1, R+1, R+1) float32, negative inside the ball


def _sample() -> Gmdag:
    lattice = _sphere_lattice(32, 9.3, (15.2, 16.7, 14.1))  # (33, 33, 33)
    classes = np.zeros((4, 4, 4), np.uint8)  # (4, 4, 4)
    classes[1:3, 1:3, 1:3] = 2
    return build_gmdag(
        lattice,
        origin=(-1.5, 2.0, 0.25),
        voxel_size=0.125,
        brick_class=classes,
        spawns=np.array([[0.0, 3.0, 1.0], [-1.5, 2.0, 0.25]]),
        class_names=("unknown", "wall", "floor"),
        bounds=((-1.0, 2.5, 0.5), (2.0, 5.0, 3.5)),
        flags=FLAG_INSIDE_SEEDS,
    )


def _refresh_crc(data: bytes) -> bytes:
    body = data[:-4]
    return body + struct.pack("<I", zlib.crc32(body))


def _patch(data: bytes, offset: int, fmt: str, *values: object) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, *values)
    return _refresh_crc(bytes(out))


def test_child_words_pack_and_unpack() -> None:
    for tag in (TAG_NODE, TAG_BRICK, TAG_FAR_FREE, TAG_FAR_SOLID):
        word = make_child(tag, 12345)
        assert child_tag(word) == tag and child_payload(word) == 12345
    assert make_child(TAG_FAR_SOLID, PAYLOAD_MASK) == 0xFFFFFFFF
    with pytest.raises(ValueError):
        make_child(4, 0)
    with pytest.raises(ValueError):
        make_child(TAG_NODE, PAYLOAD_MASK + 1)


def test_round_trip_is_byte_exact_and_lossless(tmp_path: Path) -> None:
    g = _sample()
    data = encode_gmdag(g)
    path = tmp_path / "s.gmdag"
    write_gmdag(g, path)
    assert path.read_bytes() == data
    assert [p.name for p in tmp_path.iterdir()] == ["s.gmdag"]  # no temp file left behind
    back = read_gmdag(path)
    assert encode_gmdag(back) == data
    for f in dataclasses.fields(Gmdag):
        a, b = getattr(g, f.name), getattr(back, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), f.name
        else:
            assert a == b, f.name
    assert back.class_names == ("unknown", "wall", "floor")
    assert back.spawns.dtype == np.float32 and back.spawns.shape == (2, 3)


def test_version_1_files_stay_readable_and_decode_to_the_same_scene() -> None:
    g = _sample()
    v1, v2 = encode_gmdag(g, version=1), encode_gmdag(g)
    assert len(v2) < len(v1)
    back = decode_gmdag(v1)
    assert encode_gmdag(back, version=1) == v1 and encode_gmdag(back) == v2
    with pytest.raises(ValueError, match="version"):
        encode_gmdag(g, version=3)


def _raw_payload(g: Gmdag) -> bytes:
    return g.nodes.astype("<u4").tobytes() + g.bricks.tobytes() + g.brick_class.tobytes()


@pytest.mark.parametrize("version", [1, 2])
def test_layout_matches_the_spec(version: int) -> None:
    g = _sample()
    data = encode_gmdag(g, version=version)
    assert data[:8] == b"GMDAG\x00\r\n"
    fields = struct.unpack_from("<6I", data, 8)
    assert fields == (version, 128, 32, 8, 2, g.root)
    assert struct.unpack_from("<3dd", data, 32) == (*g.origin, g.voxel_size)
    band, step = struct.unpack_from("<2f", data, 64)
    assert band == 4.0 and step == np.float32(4.0 / 127)
    counts = struct.unpack_from("<4I", data, 72)
    assert counts == (len(g.nodes), len(g.bricks), 2, 3)
    flags, packed, reserved = struct.unpack_from("<II8s", data, 112)
    assert flags == FLAG_INSIDE_SEEDS and reserved == bytes(8)
    raw = _raw_payload(g)
    assert len(raw) == 32 * counts[0] + 730 * counts[1]
    if version == 1:
        assert packed == 0 and data[HEADER_BYTES : HEADER_BYTES + len(raw)] == raw
        stored = len(raw)
    else:
        assert zlib.decompress(data[HEADER_BYTES : HEADER_BYTES + packed]) == raw
        stored = packed
    names = b"\x07unknown\x04wall\x05floor"
    spawns = g.spawns.astype("<f4").tobytes()
    assert data[HEADER_BYTES + stored :] == spawns + names + data[-4:]
    assert len(data) == HEADER_BYTES + stored + 12 * 2 + len(names) + 4
    assert struct.unpack("<I", data[-4:])[0] == zlib.crc32(data[:-4])


def test_dense_lattice_recovers_the_field_within_quantisation() -> None:
    lattice = _sphere_lattice(32, 9.3, (15.2, 16.7, 14.1))  # (33, 33, 33)
    dense = dense_lattice(build_gmdag(lattice, origin=(0, 0, 0), voxel_size=1.0))  # (33, 33, 33)
    near = np.abs(lattice) < 3.0
    step = np.float32(4.0 / 127)
    assert np.abs(dense - lattice)[near].max() <= step
    assert (np.abs(dense) <= np.abs(lattice) + 1e-6).all()  # never farther than the input
    far = np.abs(lattice) > 5.0
    assert (np.sign(dense[far]) == np.sign(lattice[far])).all()


def _expect(data: bytes, fragment: str) -> None:
    with pytest.raises(GmdagError, match=fragment):
        decode_gmdag(data)


def test_header_defects_are_rejected_with_one_clear_error() -> None:
    data = encode_gmdag(_sample())
    _expect(data[:100], "truncated")
    _expect(b"XMDAG\x00\r\n" + data[8:], "bad magic")
    _expect(_patch(data, 8, "<I", 3), "version")
    _expect(_patch(data, 12, "<I", 64), "header_bytes")
    _expect(data[:-1] + bytes([data[-1] ^ 1]), "checksum")
    _expect(data[:200] + bytes([data[200] ^ 0x10]) + data[201:], "checksum")
    _expect(_patch(data, 16, "<I", 48), "power of two")
    _expect(_patch(data, 16, "<I", 8192), "power of two")
    _expect(_patch(data, 20, "<I", 4), "brick_cells")
    _expect(_patch(data, 24, "<I", 3), "levels")
    _expect(_patch(data, 32, "<d", float("nan")), "origin")
    _expect(_patch(data, 56, "<d", 0.0), "voxel_size")
    _expect(_patch(data, 56, "<d", float("inf")), "voxel_size")
    _expect(_patch(data, 56, "<d", 1e307), "max corner")
    _expect(_patch(data, 64, "<f", -4.0), "band")
    _expect(_patch(data, 64, "<f", float("nan")), "band")
    _expect(_patch(data, 68, "<f", 0.05), "quant_step")
    _expect(_patch(data, 88, "<f", float("inf")), "bounds")
    _expect(_patch(data, 88, "<f", 3.0), "inverted")
    _expect(_patch(data, 100, "<f", 100.0), "inside the cube")
    _expect(_patch(data, 112, "<I", 4), "flag")
    _expect(_patch(data, 120, "<I", 1), "reserved")
    _expect(_patch(encode_gmdag(_sample(), version=1), 116, "<I", 1), "reserved")  # no payload_bytes in v1


def test_size_defects_are_rejected() -> None:
    data = encode_gmdag(_sample(), version=1)
    _expect(_refresh_crc(data[:-4] + b"\x00" + data[-4:]), "trailing")
    _expect(_refresh_crc(data[:-5] + data[-4:]), "truncated")
    _expect(_patch(data, 72, "<I", 0xFFFFFFFF), "truncated")
    _expect(_patch(data, 76, "<I", 0xFFFFFF), "truncated")
    _expect(_patch(data, 84, "<I", 300), "class_count")
    _expect(_patch(data, 84, "<I", 4), "truncated")


def _with_node_word(data: bytes, node: int, child: int, word: int) -> bytes:
    return _patch(data, HEADER_BYTES + 32 * node + 4 * child, "<I", word)


def test_structure_defects_are_rejected() -> None:
    g = _sample()
    data = encode_gmdag(g, version=1)  # raw payload: node words can be patched in place
    assert child_tag(g.root) == TAG_NODE and len(g.nodes) >= 2
    n, b = len(g.nodes), len(g.bricks)
    node_child = next(c for c in range(8) if child_tag(int(g.nodes[0, c])) == TAG_NODE)
    leaf_parent = next(i for i in range(n) if (g.nodes[i] >> 30 == TAG_BRICK).any())
    brick_child = next(c for c in range(8) if child_tag(int(g.nodes[leaf_parent, c])) == TAG_BRICK)
    _expect(_with_node_word(data, 0, node_child, make_child(TAG_NODE, n)), "out of range")
    _expect(_with_node_word(data, 0, node_child, make_child(TAG_NODE, 0)), "not larger")
    _expect(_with_node_word(data, leaf_parent, brick_child, make_child(TAG_BRICK, b)), "out of range")
    _expect(_with_node_word(data, 0, node_child, make_child(TAG_BRICK, 0)), "brick at depth")
    _expect(_with_node_word(data, leaf_parent, brick_child, make_child(TAG_NODE, n - 1)), "brick depth")
    _expect(_patch(data, 28, "<I", make_child(TAG_FAR_FREE, 5)), "not reachable")
    _expect(_patch(data, 28, "<I", make_child(TAG_BRICK, 0)), "brick at depth")


def _tiny(nodes: list[list[int]], root: int) -> Gmdag:
    return Gmdag(
        resolution=64,
        levels=3,
        root=root,
        origin=(0.0, 0.0, 0.0),
        voxel_size=1.0,
        band=4.0,
        quant_step=float(np.float32(4.0 / 127)),
        nodes=np.array(nodes, np.uint32).reshape(-1, 8),
        bricks=np.zeros((0, 729), np.int8),
        brick_class=np.zeros(0, np.uint8),
        spawns=np.zeros((0, 3), np.float32),
        class_names=("unknown",),
        bounds_min=(1.0, 1.0, 1.0),
        bounds_max=(2.0, 2.0, 2.0),
        flags=0,
    )


def test_hand_made_dags_reach_each_node_at_one_depth() -> None:
    far, solid = make_child(TAG_FAR_FREE, 7), make_child(TAG_FAR_SOLID, 0)
    twice = _tiny([[1, 2, far, far, far, far, far, far], [2, *[far] * 7], [solid, *[far] * 7]], 0)
    with pytest.raises(GmdagError, match="two depths"):
        encode_gmdag(twice)
    shared = _tiny([[1, 1, far, far, far, far, far, far], [2, *[far] * 7], [solid, *[far] * 7]], 0)
    assert decode_gmdag(encode_gmdag(shared)).nodes.shape == (3, 8)
    with pytest.raises(GmdagError, match="not reachable"):
        encode_gmdag(_tiny([[1, *[far] * 7], [2, *[far] * 7], [solid, *[far] * 7], [far] * 8], 0))
    with pytest.raises(GmdagError, match="not larger"):
        encode_gmdag(_tiny([[1, *[far] * 7], [1, *[far] * 7], [solid, *[far] * 7]], 0))


def test_payload_defects_are_rejected() -> None:
    g = _sample()
    data = encode_gmdag(g, version=1)
    off_class = HEADER_BYTES + 32 * len(g.nodes) + 729 * len(g.bricks)
    _expect(_patch(data, off_class, "<B", 3), "class id")
    off_spawns = off_class + len(g.bricks)
    _expect(_patch(data, off_spawns, "<f", float("nan")), "non-finite")
    _expect(_patch(data, off_spawns, "<f", -100.0), "outside the cube")
    off_names = off_spawns + 24
    _expect(_patch(data, off_names + 1, "<B", 0xFF), "UTF-8")
    _expect(_patch(data, off_names, "<B", 200), "class name")


def _with_stream(data: bytes, stream: bytes, **counts: int) -> bytes:
    """A version 2 file with its payload stream replaced (payload_bytes and the given counts patched)."""
    packed = struct.unpack_from("<I", data, 116)[0]
    out = bytearray(data[:HEADER_BYTES] + stream + data[HEADER_BYTES + packed :])
    struct.pack_into("<I", out, 116, len(stream))
    for name, value in counts.items():
        struct.pack_into("<I", out, {"nodes": 72, "bricks": 76}[name], value)
    return _refresh_crc(bytes(out))


def test_compressed_payload_defects_are_rejected() -> None:
    g = _sample()
    data = encode_gmdag(g)
    raw = _raw_payload(g)
    stream = zlib.compress(raw)
    assert decode_gmdag(_with_stream(data, stream)).bricks.shape == g.bricks.shape  # any zlib level reads
    broken = bytearray(stream)
    broken[-2] ^= 0x55  # the stream's Adler-32
    _expect(_with_stream(data, bytes(broken)), "corrupt")
    _expect(_with_stream(data, stream[:-6]), "ends early")
    _expect(_with_stream(data, zlib.compress(raw[:-730])), "ends early")
    _expect(_with_stream(data, zlib.compress(raw + bytes(730))), "more than")
    _expect(_with_stream(data, stream + b"\x00\x01"), "stray bytes")
    _expect(_with_stream(data, stream, bricks=len(g.bricks) + 1), "ends early")
    _expect(_with_stream(data, stream, bricks=0xFFFFFFF), "more than a")  # a bomb is refused up front
    _expect(_patch(data, 116, "<I", 0xFFFFFFF), "truncated")
    # a defect inside the compressed payload is found by the same checks as in version 1
    nodes = g.nodes.copy()
    nodes[0, 0] = make_child(TAG_NODE, len(g.nodes))
    bad = nodes.astype("<u4").tobytes() + raw[32 * len(g.nodes) :]
    _expect(_with_stream(data, zlib.compress(bad)), "out of range")


def test_encoder_refuses_invalid_gmdags() -> None:
    g = _sample()
    with pytest.raises(GmdagError, match="class id"):
        encode_gmdag(dataclasses.replace(g, class_names=("unknown",)))
    with pytest.raises(GmdagError, match="outside the cube"):
        encode_gmdag(dataclasses.replace(g, spawns=np.array([[99.0, 0.0, 0.0]], np.float32)))
    with pytest.raises(GmdagError, match="nodes must be"):
        encode_gmdag(dataclasses.replace(g, nodes=g.nodes.astype(np.int64)))


def test_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "s.gmdag"
    g = _sample()
    write_gmdag(g, path)
    before = path.read_bytes()
    with pytest.raises(GmdagError):
        write_gmdag(dataclasses.replace(g, class_names=("unknown",)), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.gmdag"]
