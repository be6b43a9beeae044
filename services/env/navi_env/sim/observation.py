"""DistanceMatrix v2: the (N, 3, Az, El) observation and the view statistics the rewards read.

Channels: 0 depth / horizon in [0, 1] (1 = miss), rounded to float16 (10 bits of mantissa: 0.05% of
the depth); 1 semantic: 0 for a miss, 0.5 + 0.5 * class / 255 for a hit (so any hit reads >= 0.5, class
0 "unknown" reads 0.5); 2 delta depth: channel 0 minus its value one step earlier (exact in float32,
both being float16 values in [0, 1]), 0 right after a reset. Layout of (Az, El): see navi_env.rays.

So an observation is fully given by its compact form (`pack`): channel 0 as float16 and the semantic
code as one byte per ray (3 bytes per ray instead of 12), with channel 2 recomputed from two
consecutive frames and the reset flags (`unpack`, bit-identical to what the env wrote). Rollouts store
that form (navi_learner.ppo.rollout).

Two ways to compute a step's observation and view statistics with the same results: `observe_ref`
(eager kernels, about ten passes over (N, R); the CPU path) and `observe` (one torch.compile'd pass
that writes the three channels and counts the rays of the statistics; the CUDA path).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from navi_env.config import RewardConfig

CHANNELS = 3
"""C: depth, semantic, delta depth."""
MARK_BANDS = 16
"""Point-goal episodes paint the goal into channel 1 as -(b + 1) / MARK_BANDS for distance band b
(navi_env.sim.goals); stored compact as semantic code FIRST_MARK_CODE + b."""
FIRST_MARK_CODE = 256 - MARK_BANDS
"""240: codes 240-255 are the goal mark where an env paints one (classes then stay at most 238)."""


@dataclass(frozen=True)
class ViewStats:
    """Per-actor statistics of one view, each (N,) float32."""

    void: torch.Tensor  # fraction of rays that missed (saw the horizon)
    near: torch.Tensor  # fraction of rays closer than near_distance
    mid: torch.Tensor  # fraction of rays in [mid_range_min, mid_range_max]
    front_mid: torch.Tensor  # the same fraction over the front half (|azimuth| < 90 degrees)
    clearance: (
        torch.Tensor
    )  # meters to the nearest surface any ray sees (the shortest depth; horizon if none)


def write_observation(
    obs: torch.Tensor,
    depth: torch.Tensor,
    semantic: torch.Tensor,
    hit: torch.Tensor,
    fresh: torch.Tensor,
    horizon: float,
    prev: torch.Tensor | None = None,
) -> None:
    """Write obs (N, 3, Az, El) in place from depth (N, R) meters in [0, horizon], the tracer's semantic
    output (N, R) uint8 (0 miss, 1 + class id on a hit) and hit (N, R) bool, which must be semantic > 0.

    `fresh` (N,) bool marks actors whose previous frame belongs to another episode: delta is 0 there.
    `prev` (N, 3, Az, El) holds the previous frame (an env that writes two buffers in turn); by default
    it is obs itself, overwritten here. Written as few full passes over (N, R) as eager PyTorch allows:
    this runs every step for every ray.
    """
    n, r = depth.shape
    ch0, ch1, ch2 = obs[:, 0].view(n, r), obs[:, 1].view(n, r), obs[:, 2].view(n, r)  # (N, R) views
    before = ch0 if prev is None else prev[:, 0].view(n, r)  # (N, R) the previous frame's channel 0
    now = round_to_half(torch.mul(depth, 1.0 / horizon))  # (N, R) channel 0
    torch.sub(now, before, out=ch2)  # now - previous, exact (float16 values in [0, 1])
    ch2.masked_fill_(fresh[:, None], 0.0)
    ch0.copy_(now)
    _semantic_channel(ch1, semantic, hit)


def round_to_half(x: torch.Tensor) -> torch.Tensor:
    """x (any shape) float32 rounded to the nearest float16 value (ties to even), kept as float32: the
    same values as x.half().float() for |x| <= 65504. Spelled out in integer operations because
    inductor drops a float32 -> float16 -> float32 round trip as a no-op (torch 2.11 and 2.13)."""
    bits = x.view(torch.int32)  # same shape, the float's bits
    normal = ((bits + (0x0FFF + ((bits >> 13) & 1))) & -8192).view(torch.float32)  # 10 mantissa bits kept
    tiny = torch.round(x * 2.0**24) * 2.0**-24  # below 2^-14 float16 is fixed point in steps of 2^-24
    return torch.where(x.abs() < 2.0**-14, tiny, normal)


def _semantic_channel(out: torch.Tensor, semantic: torch.Tensor, hit: torch.Tensor) -> None:
    """Channel 1 into out (N, R) float32 from semantic (N, R) uint8 and hit (N, R) bool."""
    # hit: 0.5 + 0.5 * (semantic - 1) / 255 = semantic * 0.5/255 + (0.5 - 0.5/255) * hit; miss: 0
    torch.mul(semantic, 0.5 / 255.0, out=out)
    out.add_(hit, alpha=0.5 - 0.5 / 255.0)


def semantic_table(device: torch.device | str, goal_marks: bool = False) -> torch.Tensor:
    """Channel 1 of each of the 256 semantic codes, (256,) float32 on `device`, computed by the same
    eager kernels as write_observation (so a lookup in it gives exactly their values). With
    `goal_marks`, codes FIRST_MARK_CODE + b read as the goal mark of band b instead (what `unpack` needs
    for a point-goal env's observations)."""
    codes = torch.arange(256, dtype=torch.uint8, device=device)[None]  # (1, 256) uint8
    table = torch.empty(1, 256, dtype=torch.float32, device=device)  # (1, 256) float32
    _semantic_channel(table, codes, codes > 0)
    if goal_marks:
        bands = torch.arange(MARK_BANDS, device=device)  # (B,)
        table[0, FIRST_MARK_CODE:] = -(bands + 1).to(torch.float32) / MARK_BANDS
    return table[0]


def pack(obs: torch.Tensor, depth16: torch.Tensor, semantic: torch.Tensor) -> None:
    """The compact form of observations obs (B, 3, Az, El) float32: channel 0 into depth16 (B, Az, El)
    float16 and the semantic code of channel 1 into semantic (B, Az, El) uint8. Exact for observations
    this module wrote (see unpack), goal marks included (negative channel 1, codes FIRST_MARK_CODE and
    up); anything else comes back different (train.collect checks once)."""
    depth16.copy_(obs[:, 0])
    ch1 = obs[:, 1]  # (B, Az, El): 0 (miss), table[code] = code * 0.5/255 + (0.5 - 0.5/255), or a mark
    hit = (ch1 - (0.5 - 0.5 / 255.0)) * 510.0  # (B, Az, El) within ulps of the code of a hit
    mark = (FIRST_MARK_CODE - 1) - ch1 * MARK_BANDS  # (B, Az, El) the code of a goal mark
    code = torch.where(ch1 > 0.0, hit, torch.where(ch1 < 0.0, mark, 0.0))  # (B, Az, El)
    semantic.copy_(code.round_().clamp_(0.0, 255.0))


def unpack(
    depth16: torch.Tensor, semantic: torch.Tensor, fresh: torch.Tensor, table: torch.Tensor
) -> torch.Tensor:
    """Observations (T, B, 3, Az, El) float32 from their compact form: depth16 (T + 1, B, Az, El) float16
    holds channel 0 of the T frames and, first, of the frame before them; semantic (T, B, Az, El) uint8
    the codes of the T frames; fresh (T, B) bool marks frames whose previous frame is from another
    episode. Bit-identical to what write_observation / observe wrote for those frames."""
    ch0 = depth16.to(torch.float32)  # (T + 1, B, Az, El)
    now = ch0[1:]  # (T, B, Az, El)
    delta = torch.where(fresh[:, :, None, None], 0.0, now - ch0[:-1])  # (T, B, Az, El)
    return torch.stack((now, table[semantic.to(torch.int64)], delta), dim=2)  # (T, B, 3, Az, El)


def is_front(azimuth: torch.Tensor, azimuth_bins: int) -> torch.Tensor:
    """Whether azimuth bins (any shape, int64) look forward, cos(2*pi*a/Az) > 0: 4a < Az or 4a > 3 Az."""
    return (4 * azimuth < azimuth_bins) | (4 * azimuth > 3 * azimuth_bins)


def front_bin_count(azimuth_bins: int) -> int:
    """Number of azimuth bins in the front half (see is_front)."""
    return int(is_front(torch.arange(azimuth_bins), azimuth_bins).sum())


def view_stats(depth: torch.Tensor, hit: torch.Tensor, azimuth_bins: int, cfg: RewardConfig) -> ViewStats:
    """Statistics of views: depth (N, R) meters, hit (N, R) bool; rays ordered as navi_env.rays says.

    Near and mid-range rays are counted by depth (a miss reads the horizon, beyond both bands). The
    front half is the azimuth bins that look forward (see `is_front`). The clearance is the shortest
    depth of the view: with the full-sphere pattern it is the distance to the nearest surface, within
    the pattern's angular spacing (docs/SIMULATION.md).
    """
    n, r = depth.shape
    el = r // azimuth_bins
    front_az = is_front(torch.arange(azimuth_bins, device=depth.device), azimuth_bins)  # (Az,) bool
    mid = (depth >= cfg.mid_range_min) & (depth <= cfg.mid_range_max)  # (N, R) bool
    mid_az = mid.view(n, azimuth_bins, el).sum(dim=2, dtype=torch.float32)  # (N, Az) rays per azimuth
    front = (mid_az * front_az).sum(dim=1)  # (N,)
    return ViewStats(
        void=1.0 - hit.sum(dim=1, dtype=torch.float32) / r,
        near=(depth < cfg.near_distance).sum(dim=1, dtype=torch.float32) / r,
        mid=mid_az.sum(dim=1) / r,
        front_mid=front / (front_bin_count(azimuth_bins) * el),
        clearance=depth.amin(dim=1),
    )


def observe_ref(
    obs: torch.Tensor,
    depth: torch.Tensor,
    semantic: torch.Tensor,
    fresh: torch.Tensor,
    stats_depth: torch.Tensor,
    stats_semantic: torch.Tensor,
    horizon: float,
    cfg: RewardConfig,
    prev: torch.Tensor | None = None,
) -> ViewStats:
    """One step's observation stage with eager kernels: obs (N, 3, Az, El) in place from the sensed
    depth (N, R) float32 and semantic (N, R) uint8 (see write_observation; `prev` as there), and the
    view statistics of the exact trace, stats_depth (N, R) float32 and stats_semantic (N, R) uint8 (see
    view_stats)."""
    hit = semantic > 0  # (N, R) bool
    write_observation(obs, depth, semantic, hit, fresh, horizon, prev)
    stats_hit = hit if stats_semantic is semantic else stats_semantic > 0  # (N, R) bool
    return view_stats(stats_depth, stats_hit, obs.shape[2], cfg)


def observe(
    obs: torch.Tensor,
    depth: torch.Tensor,
    semantic: torch.Tensor,
    fresh: torch.Tensor,
    stats_depth: torch.Tensor,
    stats_semantic: torch.Tensor,
    table: torch.Tensor,
    horizon: float,
    cfg: RewardConfig,
    prev: torch.Tensor | None = None,
) -> ViewStats:
    """observe_ref in one compiled pass over (N, R) (plus a few (N,) kernels); `table` is
    semantic_table(device). Compiled on the first call for each shape (seconds to a minute): make that
    call before recording a CUDA graph. Same results as observe_ref, bit for bit."""
    n, r = depth.shape
    az = obs.shape[2]
    ch = obs.view(n, CHANNELS, r)  # (N, 3, R) view of obs
    # a one-buffer env reads channel 0 before overwriting it; a two-buffer env reads the other buffer's.
    # Two compiled functions: passing ch0 a second time would make its inputs alias (slower code)
    first: tuple[torch.Tensor, ...] = (ch[:, 0], ch[:, 1], ch[:, 2])  # 3 x (N, R) views of obs
    if prev is not None:
        first += (prev.view(n, CHANNELS, r)[:, 0],)  # (N, R) the previous frame's channel 0
    with torch.no_grad():  # one grad mode for every call: the compiled code is never re-specialised
        counts, clearance = _compiled_pass(prev is not None)(
            *first,
            depth,
            semantic,
            fresh,
            stats_depth,
            stats_semantic,
            table,
            horizon,
            az,
            cfg.near_distance,
            cfg.mid_range_min,
            cfg.mid_range_max,
        )
    return _stats_from_counts(counts, clearance, r, az)


@functools.cache
def _compiled_pass(two_buffers: bool) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """_fused_pass (or _fused_pass_from, for an env with two observation buffers) compiled once per
    process (shapes specialised first, dynamic once a second env size appears). Not fullgraph: past
    dynamo's recompile limit it runs eagerly, with the same values, instead of failing the ninth
    differently sized env of a process."""
    return torch.compile(_fused_pass_from if two_buffers else _fused_pass)


def _fused_pass(
    ch0: torch.Tensor, ch1: torch.Tensor, ch2: torch.Tensor, *rest: Any
) -> tuple[torch.Tensor, torch.Tensor]:
    """_fused_pass_from for a one-buffer env: the previous frame's channel 0 is ch0 itself, read before
    it is overwritten (`rest`: _fused_pass_from's arguments after `before`)."""
    return _fused_pass_from(ch0, ch1, ch2, ch0, *rest)


def _fused_pass_from(
    ch0: torch.Tensor,
    ch1: torch.Tensor,
    ch2: torch.Tensor,
    before: torch.Tensor,
    depth: torch.Tensor,
    semantic: torch.Tensor,
    fresh: torch.Tensor,
    stats_depth: torch.Tensor,
    stats_semantic: torch.Tensor,
    table: torch.Tensor,
    horizon: float,
    azimuth_bins: int,
    near_distance: float,
    mid_min: float,
    mid_max: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Writes the channels ch0, ch1, ch2 (N, R) float32 (views into obs; `before` (N, R) is the previous
    frame's channel 0, from the other buffer of a two-buffer env) in place and returns the ray
    counts (N, 4) int32 [hits, near, mid, mid in the front half] of stats_depth and stats_semantic and
    the shortest depth (N,) float32 of stats_depth. Every value is computed by the same float32
    operation as in write_observation and view_stats."""
    r = depth.shape[1]
    el = r // azimuth_bins
    now = round_to_half(depth * (1.0 / horizon))  # (N, R) channel 0
    ch2.copy_(torch.where(fresh[:, None], 0.0, now - before))
    ch0.copy_(now)
    ch1.copy_(table[semantic.to(torch.int64)])
    azimuth = torch.arange(r, device=depth.device) // el  # (R,) int64 azimuth bin of each ray
    mid = (stats_depth >= mid_min) & (stats_depth <= mid_max)  # (N, R) bool
    front = mid & is_front(azimuth, azimuth_bins)  # (N, R) bool
    counts = torch.stack(
        (
            (stats_semantic > 0).sum(dim=1, dtype=torch.int32),
            (stats_depth < near_distance).sum(dim=1, dtype=torch.int32),
            mid.sum(dim=1, dtype=torch.int32),
            front.sum(dim=1, dtype=torch.int32),
        ),
        dim=1,
    )  # (N, 4) int32
    return counts, stats_depth.amin(dim=1)


def _stats_from_counts(counts: torch.Tensor, clearance: torch.Tensor, r: int, azimuth_bins: int) -> ViewStats:
    """ViewStats from the ray counts (N, 4) int32 and shortest depths (N,) of _fused_pass, with
    view_stats' float32 operations (counts below 2^24 are exact in float32, so the results are identical)."""
    el = r // azimuth_bins
    f = counts.to(torch.float32)  # (N, 4)
    return ViewStats(
        void=1.0 - f[:, 0] / r,
        near=f[:, 1] / r,
        mid=f[:, 2] / r,
        front_mid=f[:, 3] / (front_bin_count(azimuth_bins) * el),
        clearance=clearance,
    )
