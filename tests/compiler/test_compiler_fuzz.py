"""Fuzz the .gmdag reader: every mutated file must raise GmdagError or decode to a valid file.

Seeds are written in both format versions (1: raw payload, 2: zlib payload); one mutation rewrites a
word inside the inflated version 2 payload and compresses it again, so the structural checks are
fuzzed behind the compression too.

3,000 cases by default; `pytest --long` runs 100,000 (docs/COMPILER.md), NAVI_FUZZ_CASES=N any
count. The seed is fixed, so a failure names a reproducible case number.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable

import numpy as np

from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import (
    HEADER_BYTES,
    TAG_FAR_FREE,
    TAG_FAR_SOLID,
    Gmdag,
    GmdagError,
    decode_gmdag,
    encode_gmdag,
    make_child,
)

_INTERESTING_U32 = [
    0,
    1,
    2,
    3,
    7,
    8,
    9,
    16,
    31,
    32,
    64,
    127,
    128,
    255,
    256,
    4096,
    8192,
    0x3FFFFFFF,
    0x40000000,
    0x7FFFFFFF,
    0x80000000,
    0xBFFFFFFF,
    0xC0000000,
    0xFFFFFFFE,
    0xFFFFFFFF,
]
_INTERESTING_F = [
    0.0,
    -0.0,
    1.0,
    -1.0,
    0.5,
    4.0,
    1e-30,
    1e30,
    1e300,
    float("inf"),
    float("-inf"),
    float("nan"),
]
# (offset, format) of every header field a mutation may rewrite
_HEADER_FIELDS = (
    [(8 + 4 * i, "<I") for i in range(6)]
    + [(32 + 8 * i, "<d") for i in range(4)]
    + [
        (64, "<f"),
        (68, "<f"),
        *[(72 + 4 * i, "<I") for i in range(4)],
        *[(88 + 4 * i, "<f") for i in range(6)],
        (112, "<I"),
        (116, "<I"),
        (120, "<I"),
        (124, "<I"),
    ]
)


def _seeds() -> list[bytes]:
    x = np.arange(33, dtype=np.float64)  # (33,)
    gx, gy, gz = np.meshgrid(x, x, x, indexing="ij")  # (33, 33, 33) each
    ball = (np.sqrt((gx - 15.5) ** 2 + (gy - 17.2) ** 2 + (gz - 14.0) ** 2) - 8.7).astype(np.float32)
    classes = np.zeros((4, 4, 4), np.uint8)  # (4, 4, 4)
    classes[2:] = 1
    sphere = build_gmdag(
        ball,
        origin=(-2.0, 0.0, 1.0),
        voxel_size=0.25,
        brick_class=classes,
        spawns=np.array([[0.0, 1.0, 2.0]]),
        class_names=("unknown", "wäll"),
        flags=1,
    )
    single = np.full((9, 9, 9), 5.0, np.float32)  # (9, 9, 9)
    single[3:6, 3:6, 3:6] = -0.5
    far, solid = make_child(TAG_FAR_FREE, 40), make_child(TAG_FAR_SOLID, 3)
    shared = Gmdag(
        resolution=64,
        levels=3,
        root=0,
        origin=(0.0, 0.0, 0.0),
        voxel_size=1.0,
        band=4.0,
        quant_step=float(np.float32(4.0 / 127)),
        nodes=np.array(
            [[1, 1, far, far, far, far, far, far], [2, 2, *[far] * 6], [solid, *[far] * 7]], np.uint32
        ),
        bricks=np.zeros((0, 729), np.int8),
        brick_class=np.zeros(0, np.uint8),
        spawns=np.zeros((0, 3), np.float32),
        class_names=("unknown",),
        bounds_min=(1.0, 1.0, 1.0),
        bounds_max=(3.0, 3.0, 3.0),
        flags=0,
    )
    scenes = [sphere, build_gmdag(single, origin=(0, 0, 0), voxel_size=1.0), shared]
    return [encode_gmdag(g, version=v) for g in scenes for v in (1, 2)]


def _crc(body: bytearray) -> bytes:
    return bytes(body[:-4]) + struct.pack("<I", zlib.crc32(bytes(body[:-4])))


def _flip(rng: np.random.Generator, data: bytes) -> bytes:
    if len(data) < 5:
        return data + b"\x00"
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        pos = int(rng.integers(0, len(out)))
        out[pos] ^= 1 << int(rng.integers(0, 8))
    return _crc(out) if rng.random() < 0.8 else bytes(out)


def _truncate(rng: np.random.Generator, data: bytes) -> bytes:
    if not data:
        return data
    cut = int(rng.integers(0, len(data)))
    return data[:cut] if rng.random() < 0.5 else _crc(bytearray(data[:cut] + b"\0\0\0\0"))


def _extend(rng: np.random.Generator, data: bytes) -> bytes:
    extra = rng.integers(0, 256, int(rng.integers(1, 64))).astype(np.uint8).tobytes()
    return _crc(bytearray(data[:-4] + extra + data[-4:])) if rng.random() < 0.7 else data + extra


def _header_field(rng: np.random.Generator, data: bytes) -> bytes:
    out = bytearray(data)
    if len(out) < HEADER_BYTES + 4:
        return data
    offset, fmt = _HEADER_FIELDS[int(rng.integers(0, len(_HEADER_FIELDS)))]
    if fmt == "<I":
        old = struct.unpack_from(fmt, out, offset)[0]
        choice = [*_INTERESTING_U32, old + 1, max(old - 1, 0), int(rng.integers(0, 2**32))]
        value: float = choice[int(rng.integers(0, len(choice)))] & 0xFFFFFFFF
    else:
        old_f = struct.unpack_from(fmt, out, offset)[0]
        choice_f = [*_INTERESTING_F, old_f * 2, -old_f, old_f + 1e-3, float(rng.normal() * 100)]
        value = choice_f[int(rng.integers(0, len(choice_f)))]
        if fmt == "<f":
            with np.errstate(over="ignore"):
                value = float(np.float32(value))
    struct.pack_into(fmt, out, offset, value)
    return _crc(out)


def _body_word(rng: np.random.Generator, data: bytes) -> bytes:
    out = bytearray(data)
    end = len(out) - 4
    if end - HEADER_BYTES < 4:
        return bytes(out)
    pos = HEADER_BYTES + 4 * int(rng.integers(0, (end - HEADER_BYTES) // 4))
    tag = int(rng.integers(0, 4)) << 30
    choice = [*_INTERESTING_U32, tag | int(rng.integers(0, 8)), int(rng.integers(0, 2**32))]
    struct.pack_into("<I", out, pos, choice[int(rng.integers(0, len(choice)))])
    return _crc(out)


def _payload_word(rng: np.random.Generator, data: bytes) -> bytes:
    """Rewrite one u32 of a version 2 file's inflated payload and compress it again."""
    if len(data) < HEADER_BYTES + 4 or struct.unpack_from("<I", data, 8)[0] != 2:
        return data
    packed = struct.unpack_from("<I", data, 116)[0]
    try:
        raw = bytearray(zlib.decompress(data[HEADER_BYTES : HEADER_BYTES + packed]))
    except zlib.error:
        return data
    if len(raw) >= 4:
        pos = 4 * int(rng.integers(0, len(raw) // 4))
        choice = [*_INTERESTING_U32, int(rng.integers(0, 4)) << 30 | int(rng.integers(0, 8))]
        struct.pack_into("<I", raw, pos, choice[int(rng.integers(0, len(choice)))])
    stream = zlib.compress(bytes(raw))
    out = bytearray(data[:HEADER_BYTES] + stream + data[HEADER_BYTES + packed :])
    struct.pack_into("<I", out, 116, len(stream))
    return _crc(out)


_MUTATIONS: list[Callable[[np.random.Generator, bytes], bytes]] = [
    _flip,
    _truncate,
    _extend,
    _header_field,
    _body_word,
    _payload_word,
]


def test_mutated_files_raise_gmdag_error_or_revalidate(fuzz_cases: int) -> None:
    seeds = _seeds()
    for i, data in enumerate(seeds):
        assert encode_gmdag(decode_gmdag(data), version=1 + i % 2) == data
    rng = np.random.default_rng(20261122)
    accepted = 0
    for case in range(fuzz_cases):
        data = seeds[case % len(seeds)]
        for _ in range(int(rng.integers(1, 3))):
            data = _MUTATIONS[int(rng.integers(0, len(_MUTATIONS)))](rng, data)
        try:
            g = decode_gmdag(data)
        except GmdagError:
            continue
        except Exception as exc:  # any other exception is the bug this test hunts
            raise AssertionError(f"case {case}: {type(exc).__name__}: {exc}") from exc
        accepted += 1
        raw = encode_gmdag(g, version=1)
        if struct.unpack_from("<I", data, 8)[0] == 1:
            assert raw == data, f"case {case}: an accepted file does not re-encode to itself"
        # a version 2 stream may differ in encoding (zlib level, padding bits), never in content
        assert encode_gmdag(decode_gmdag(encode_gmdag(g)), version=1) == raw, f"case {case}"
    assert accepted < fuzz_cases  # most mutations must be caught
