"""MurmurHash3 x86_32 (Austin Appleby's public-domain algorithm), seed 0 by default.

The DAG stage hashes bricks and nodes to group deduplication candidates; byte equality decides.
`murmur3_32` hashes one byte string; `murmur3_32_rows` hashes every row of a (K, n) uint8 array at
once (the same result per row). The C++ core (csrc/murmur.h) implements the same function.
"""

from __future__ import annotations

import numpy as np

_C1 = 0xCC9E2D51
_C2 = 0x1B873593
_M32 = 0xFFFFFFFF


def _rotl32(x: int, r: int) -> int:
    return ((x << r) | (x >> (32 - r))) & _M32


def _fmix32(h: int) -> int:
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & _M32
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & _M32
    h ^= h >> 16
    return h


def murmur3_32(data: bytes, seed: int = 0) -> int:
    """MurmurHash3 x86_32 of `data` (the slow, obviously correct twin of `murmur3_32_rows`)."""
    h = seed & _M32
    n_blocks = len(data) // 4
    for i in range(n_blocks):
        k = int.from_bytes(data[4 * i : 4 * i + 4], "little")
        k = (_rotl32((k * _C1) & _M32, 15) * _C2) & _M32
        h ^= k
        h = (_rotl32(h, 13) * 5 + 0xE6546B64) & _M32
    tail = data[4 * n_blocks :]
    if tail:
        k = int.from_bytes(tail, "little")
        k = (_rotl32((k * _C1) & _M32, 15) * _C2) & _M32
        h ^= k
    h ^= len(data) & _M32
    return _fmix32(h)


def _rotl32_np(x: np.ndarray, r: int) -> np.ndarray:
    return (x << np.uint32(r)) | (x >> np.uint32(32 - r))


def murmur3_32_rows(rows: np.ndarray, seed: int = 0) -> np.ndarray:
    """MurmurHash3 x86_32 of every row of `rows` ((K, n) uint8); returns (K,) uint32."""
    if rows.ndim != 2 or rows.dtype != np.uint8:
        raise ValueError(f"rows must be (K, n) uint8, got {rows.shape} {rows.dtype}")
    k_rows, n = rows.shape
    n_blocks = n // 4
    c1, c2 = np.uint32(_C1), np.uint32(_C2)
    h = np.full(k_rows, seed & _M32, np.uint32)  # (K,) uint32
    blocks = np.ascontiguousarray(rows[:, : 4 * n_blocks]).view("<u4")  # (K, n // 4) uint32
    with np.errstate(over="ignore"):
        for i in range(n_blocks):
            k = _rotl32_np(blocks[:, i] * c1, 15) * c2  # (K,) uint32
            h = _rotl32_np(h ^ k, 13) * np.uint32(5) + np.uint32(0xE6546B64)
        tail = rows[:, 4 * n_blocks :].astype(np.uint32)  # (K, n % 4) uint32
        if tail.shape[1]:
            k = np.zeros(k_rows, np.uint32)  # (K,) uint32
            for j in range(tail.shape[1]):
                k |= tail[:, j] << np.uint32(8 * j)
            h ^= _rotl32_np(k * c1, 15) * c2
        h ^= np.uint32(n & _M32)
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x85EBCA6B)
        h ^= h >> np.uint32(13)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(16)
    return h
