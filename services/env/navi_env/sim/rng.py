"""Counter-based random numbers: integer hashing of (seed, stream, step, index) with tensor ops.

The same keys give bit-identical numbers on CPU and CUDA (integer arithmetic only, no generator
state), so a seeded rollout is reproducible on either device and CPU and CUDA rollouts agree.
"""

from __future__ import annotations

import math

import torch

_MASK32 = 0xFFFFFFFF
_M1 = 0x7FEB352D
_M2 = 0x846CA68B
_GOLDEN = 0x9E3779B9

STREAM_SCENE = 1
"""Stream id of the scene choice at rotation."""
STREAM_SPAWN = 2
"""Stream id of the spawn choice."""
STREAM_YAW = 3
"""Stream id of the heading at spawn."""
STREAM_NOISE = 4
"""Stream id of the sensor's range noise."""
STREAM_DROPOUT = 5
"""Stream id of the sensor's ray dropout."""
STREAM_OBSTACLE_PLACE = 6
"""Stream id of the spawn points tried when obstacles are placed."""
STREAM_OBSTACLE_SHAPE = 7
"""Stream id of an obstacle's size, orientation, speed and path at placement."""
STREAM_OBSTACLE_WALK = 8
"""Stream id of the random walk's heading changes."""
STREAM_GOAL = 9
"""Stream id of the point-goal draw at a spawn."""


def mix32(x: torch.Tensor) -> torch.Tensor:
    """Bijective 32-bit integer mix of int64 values holding 32-bit numbers (same shape, int64)."""
    x = x & _MASK32
    x = x ^ (x >> 16)
    x = (x * _M1) & _MASK32
    x = x ^ (x >> 15)
    x = (x * _M2) & _MASK32
    return x ^ (x >> 16)


def hash_keys(seed: torch.Tensor, stream: int, tick: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """32-bit hashes (shape of `index`, int64) of (seed, stream, tick, index); seed and tick are 0-d
    int64 tensors on index's device (device values, so a captured CUDA graph sees their updates)."""
    base = mix32(mix32(seed * _GOLDEN + stream) ^ mix32(tick))  # () int64
    return mix32(base + (index & _MASK32) * _GOLDEN)


def uniform(seed: torch.Tensor, stream: int, tick: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Uniform float32 in [0, 1) per element of `index` (int64)."""
    bits = hash_keys(seed, stream, tick, index) >> 8  # 24 bits
    return bits.to(torch.float32) * (1.0 / (1 << 24))


def normal(seed: torch.Tensor, stream: int, tick: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Standard normal float32 per element of `index` (Box-Muller on two hashed uniforms)."""
    u1, u2 = uniform(seed, stream, tick, torch.stack((2 * index, 2 * index + 1)))  # 2 x (...) in one hash
    radius = torch.sqrt(-2.0 * torch.log1p(-u1))  # log1p(-u) finite for u < 1
    return radius * torch.cos(2.0 * math.pi * u2)
