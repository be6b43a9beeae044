"""`navi bench trace --vs-nanovdb`: the benchmark's rays sphere-traced through a NanoVDB narrow band.

NanoVDB (OpenVDB's GPU form, Warp's `Volume`) is the standard sparse volume for level sets, so it is
the peer a user would pick instead of a `.gmdag`. The anchor holds the same distance samples at the
same lattice as the scene (Navi's samples sit at the corners of its R^3 cells: index (i, j, k) is
world `origin + voxel * (i, j, k)`, read through `sample_distance`), allocated by 8^3 tiles: exactly
the tiles that hold a sample within `band` voxels of the surface (every sample of every candidate tile
is tested), values clamped to +-band and `band` voxels (meters) outside the tiles, float32 (the one
value type Warp allocates and writes on the device). A Warp kernel (`nanovdb_kernel.march`) traces the
same world-space rays with trilinear samples and Navi's step and hit rules, but without its far-cube
skips: in free space it steps by at most the band. That is what a narrow-band level set without
hierarchical skipping (HDDA) costs. fVDB's HDDA ray query ships as source only (`fvdb-core`, whose CMake
build downloads NanoVDB and its other dependencies), so it is not measured here.

Two settings look for the fastest band the library allows: `scale` samples the same field on a lattice
`scale` times coarser (voxels of `scale` cells: a band of B voxels reaches `scale` times farther in
meters, in about 1 / scale^2 of the tiles, with thin walls at the mercy of the coarser samples), and
SAMPLINGS names the march: "linear" reads a trilinear sample every step, "closest-far" reads the nearest
sample alone while it bounds the distance above FAR_VOXELS (nanovdb_kernel.march's `far`).

Only when `warp` (warp-lang) imports; otherwise `NanoVDBUnavailable` with the reason.

Shapes: B agents, R rays per agent, P = B * R rays, T tiles, V = 512 T voxels.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from navi_bench.nanovdb_kernel import REFINE_ITERATIONS, SECANT_REACH, fill_kernel, march_kernel
from navi_bench.trace import TraceBenchConfig, rays_for_warp, tracer_depth
from navi_env.tracer.scene import SceneCorpus
from navi_env.tracer.trace import DEFAULT_HIT_EPSILON_VOXELS, sample_distance

TILE = 8
"""Voxels per NanoVDB leaf edge."""
BANDS = (3.0, 8.0, 24.0)
"""Narrow-band half widths (voxels) measured by default."""
TILE_REACH = (TILE - 1) / 2 * math.sqrt(3.0) + 0.5
"""Voxels from a tile's centre to its farthest voxel (3.5 sqrt 3), plus half a voxel for the samples'
rounding: a tile whose centre is farther than band + this from the surface holds no band voxel."""
CHUNK = 1 << 22
"""Voxels sampled and stored per pass while filling."""
FAR_VOXELS = 2.0
""""closest-far": the nearest-sample bound (voxels) above which a step skips the trilinear read."""
SAMPLINGS = {"linear": 0.0, "closest-far": FAR_VOXELS}
"""The marches measured: name -> the kernel's `far` (0: trilinear samples only)."""


class NanoVDBUnavailable(RuntimeError):
    """Warp cannot run this comparison (warp-lang is not installed)."""


def lattice(corpus: SceneCorpus, scale: int = 1) -> tuple[int, float]:
    """The band's lattice for scene 0 at `scale`: (samples 0..N per axis, voxel meters); scale 1 is the
    scene's own (N = R), scale k takes every k-th sample's place (N = R // k, voxels k times larger)."""
    if scale < 1:
        raise ValueError(f"the voxel scale must be at least 1, got {scale}")
    info = corpus.infos[0]
    return info.resolution // scale, info.voxel_size * scale


def candidate_tiles(corpus: SceneCorpus, band: float, scale: int = 1) -> np.ndarray:
    """(C, 3) int32 index-space min corners of the 8^3 tiles of scene 0 at `scale` (lattice) that may
    hold a sample within `band` voxels of the surface (sampled at each tile's centre, with TILE_REACH of
    slack): a superset of the band's tiles, cheap to find."""
    info = corpus.infos[0]
    n, h = lattice(corpus, scale)
    per_axis = n // TILE + 1  # tiles covering samples 0..N
    axis = torch.arange(per_axis, dtype=torch.float64) * TILE  # (A,) tile min corners, voxels
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)  # (A^3, 3)
    centres = torch.from_numpy(info.cube_min)[None, :] + (grid + (TILE - 1) / 2) * h  # (A^3, 3) meters
    keep = torch.zeros(len(grid), dtype=torch.bool)  # (A^3,)
    for start in range(0, len(grid), CHUNK):
        pts = centres[start : start + CHUNK].float().to(corpus.device)  # (C, 3) meters
        ids = torch.zeros(len(pts), dtype=torch.int64, device=corpus.device)  # (C,)
        d = sample_distance(corpus, ids, pts).cpu() / h  # (C,) voxels
        keep[start : start + len(pts)] = d.abs() <= band + TILE_REACH
    return grid[keep].numpy().astype(np.int32)


OFFSETS = np.stack(np.meshgrid(*[np.arange(TILE)] * 3, indexing="ij"), -1).reshape(-1, 3)  # (512, 3)
"""A tile's voxels relative to its min corner."""


def narrow_band(corpus: SceneCorpus, band: float, scale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The narrow band of scene 0 on its lattice at `scale`: the 8^3 tiles that hold a sample within
    `band` voxels of the surface, and no other, (T, 3) int32 index-space min corners, with their samples
    (T, 512) float32 meters clamped to +-band voxels (OFFSETS order), as a level set's narrow band is
    built."""
    info = corpus.infos[0]
    n, h = lattice(corpus, scale)
    candidates = candidate_tiles(corpus, band, scale)  # (C, 3)
    per_chunk = max(1, CHUNK // len(OFFSETS))
    tiles, values = [], []
    for start in range(0, len(candidates), per_chunk):
        part = candidates[start : start + per_chunk]  # (C', 3)
        voxels = (part[:, None, :] + OFFSETS[None]).reshape(-1, 3)  # (C' 512, 3) int
        pts = torch.from_numpy(info.cube_min + voxels * h).float().to(corpus.device)  # (C' 512, 3) meters
        ids = torch.zeros(len(pts), dtype=torch.int64, device=corpus.device)  # (C' 512,)
        d = sample_distance(corpus, ids, pts).cpu().numpy().reshape(len(part), -1)  # (C', 512) meters
        inside = (voxels <= n).all(axis=1).reshape(len(part), -1)  # (C', 512) on the lattice
        near = ((np.abs(d) <= band * h) & inside).any(axis=1)  # (C',) tiles holding a band sample
        tiles.append(part[near])
        values.append(np.clip(d[near], -band * h, band * h).astype(np.float32))
    return np.concatenate(tiles).astype(np.int32), np.concatenate(values)  # (T, 3), (T, 512)


def build_band(
    corpus: SceneCorpus, width: float, wp: Any, device: str, scale: int = 1
) -> tuple[Any, int, int]:
    """The volume of scene 0's samples within `width` voxels on its lattice at `scale`: (wp.Volume,
    tiles T, device bytes)."""
    info = corpus.infos[0]
    tiles, values = narrow_band(corpus, width, scale)  # (T, 3), (T, 512)
    h = lattice(corpus, scale)[1]
    volume = wp.Volume.allocate_by_tiles(
        wp.array(tiles, dtype=wp.int32, device=device),  # (T, 3) voxel coordinates (Warp 1.0 needs int32)
        voxel_size=h,
        bg_value=float(width * h),
        translation=wp.vec3(*(float(c) for c in info.cube_min)),
        device=device,
    )
    fill = fill_kernel(wp)
    per_chunk = max(1, CHUNK // len(OFFSETS))
    for start in range(0, len(tiles), per_chunk):
        voxels = (tiles[start : start + per_chunk, None, :] + OFFSETS[None]).reshape(-1, 3)  # (V', 3) int32
        wp.launch(
            fill,
            dim=len(voxels),
            inputs=[
                volume.id,
                wp.array(voxels.astype(np.int32), dtype=wp.vec3i, device=device),
                wp.array(values[start : start + per_chunk].reshape(-1), dtype=float, device=device),
            ],
            device=device,
        )
    wp.synchronize_device(device)
    return volume, len(tiles), int(volume.array().size)


def _warp() -> Any:
    try:
        import warp as wp
    except ImportError as exc:
        raise NanoVDBUnavailable(f"warp-lang is not installed ({exc}); pip install warp-lang") from None
    wp.config.quiet = True  # keep stdout for the one JSON object
    wp.init()
    return wp


class Marcher:
    """The benchmark's rays as Warp arrays in scene 0's index space, and the march over a band."""

    def __init__(self, corpus: SceneCorpus, cfg: TraceBenchConfig) -> None:
        self.wp = wp = _warp()
        self.corpus, self.cfg = corpus, cfg
        dev = corpus.device
        self.device = f"cuda:{dev.index or 0}" if dev.type == "cuda" else "cpu"
        self.info = corpus.infos[0]
        self.world, dirs = rays_for_warp(corpus, cfg)  # (P, 3), (P, 3) float32 world
        self.rays = len(self.world)
        self.origins: dict[int, Any] = {}  # scale -> (P, 3) origins in that lattice's index space
        self.dirs = wp.array(dirs, dtype=wp.vec3, device=self.device)
        self.depth = wp.zeros(self.rays, dtype=float, device=self.device)  # (P,) meters
        self.steps = wp.zeros(self.rays, dtype=int, device=self.device)  # (P,)
        self.kernel = march_kernel(wp)

    def launch(self, volume: Any, scale: int = 1, sampling: str = "linear") -> None:
        """One march of every ray through `volume` (a band on the lattice at `scale`) with `sampling`
        (SAMPLINGS) into self.depth and self.steps."""
        cfg = self.cfg
        n, h = lattice(self.corpus, scale)
        if scale not in self.origins:
            index = ((self.world - self.info.cube_min[None, :]) / h).astype(np.float32)  # (P, 3) voxels
            self.origins[scale] = self.wp.array(index, dtype=self.wp.vec3, device=self.device)
        args = [
            volume.id, self.origins[scale], self.dirs, float(n), float(h), cfg.horizon,
            DEFAULT_HIT_EPSILON_VOXELS, cfg.hit_slope, cfg.max_steps, REFINE_ITERATIONS, SECANT_REACH,
            SAMPLINGS[sampling], self.depth, self.steps,
        ]  # fmt: skip
        self.wp.launch(self.kernel, dim=self.rays, inputs=args, device=self.device)

    def traced(self) -> tuple[np.ndarray, np.ndarray]:
        """The last march's depth (B, R) meters and steps (B, R)."""
        b = self.cfg.agents
        return self.depth.numpy().reshape(b, -1), self.steps.numpy().reshape(b, -1)


def nanovdb_depth(
    corpus: SceneCorpus, cfg: TraceBenchConfig, band: float, scale: int = 1, sampling: str = "linear"
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (B, R) meters and steps (B, R) of the benchmark's rays through scene 0's band volume on
    its lattice at `scale`, marched with `sampling`."""
    m = Marcher(corpus, cfg)
    volume, _, _ = build_band(corpus, band, m.wp, m.device, scale)
    m.launch(volume, scale, sampling)
    m.wp.synchronize_device(m.device)
    return m.traced()


def bench_nanovdb(
    corpus: SceneCorpus,
    cfg: TraceBenchConfig,
    tracer_ms: float,
    bands: Sequence[float] = BANDS,
    scales: Sequence[int] = (1,),
    samplings: Sequence[str] = ("linear",),
) -> list[dict[str, object]]:
    """For each voxel scale and band: build the volume; for each sampling, time the march over the
    benchmark's rays and compare its depths with the tracer's. One dict per (scale, band, sampling)."""
    unknown = [s for s in samplings if s not in SAMPLINGS]
    if unknown:
        raise ValueError(f"unknown NanoVDB sampling {unknown[0]!r}: choose from {', '.join(SAMPLINGS)}")
    m = Marcher(corpus, cfg)
    wp = m.wp
    ours = tracer_depth(corpus, cfg)  # (B, R)
    out: list[dict[str, object]] = []
    for scale in scales:
        for band in bands:
            t_build = time.perf_counter()
            volume, tiles, nbytes = build_band(corpus, band, wp, m.device, scale)
            build_s = time.perf_counter() - t_build
            for sampling in samplings:
                for _ in range(cfg.warmup):
                    m.launch(volume, scale, sampling)
                wp.synchronize_device(m.device)
                t0 = time.perf_counter()
                for _ in range(cfg.launches):
                    m.launch(volume, scale, sampling)
                wp.synchronize_device(m.device)
                seconds = (time.perf_counter() - t0) / cfg.launches
                theirs, steps = m.traced()  # (B, R) each
                n = steps.astype(np.float64).ravel()  # (P,)
                both = (theirs < cfg.horizon) & (ours < cfg.horizon)  # (B, R)
                out.append(
                    {
                        "band_voxels": band,
                        "voxel_scale": scale,
                        "voxel_m": lattice(corpus, scale)[1],
                        "sampling": sampling,
                        "value_type": "float32",
                        "tiles": tiles,
                        "voxels": tiles * TILE**3,
                        "device_bytes": nbytes,
                        "build_s": build_s,
                        "ms_per_launch": seconds * 1e3,
                        "grays_per_s": m.rays / seconds / 1e9,
                        "speedup_tracer_vs_nanovdb": seconds * 1e3 / tracer_ms,
                        "mean_steps": float(n.mean()),
                        "p99_steps": float(np.quantile(n, 0.99)),
                        "median_abs_depth_diff_m": float(np.median(np.abs(theirs[both] - ours[both])))
                        if both.any()
                        else None,
                        "p99_abs_depth_diff_m": float(np.quantile(np.abs(theirs[both] - ours[both]), 0.99))
                        if both.any()
                        else None,
                        "hit_disagreement": float(((theirs < cfg.horizon) != (ours < cfg.horizon)).mean()),
                    }
                )
            del volume
    return out
