"""The Warp kernels of `navi bench trace --vs-nanovdb`: filling a NanoVDB narrow band, and sphere tracing it.

Kept without `from __future__ import annotations`, as `warp_kernel.py`: Warp reads the kernels'
annotations as types. Index space is the volume's: voxel (i, j, k) holds the distance sample at world
`origin + voxel * (i, j, k)`, which is Navi's own sample lattice (csrc/brick_sample.h: samples at
the corners of cells), so trilinear sampling in index space interpolates the same samples the same way.

The march follows Navi's step rules (csrc/ray_walk.h) without its empty-space skipping: from the entry
into the lattice's cube it steps by max(d, eps) voxels; a sample below the hit threshold eps + slope * t
that does not rise from the one before stops the ray where the line through the two meets zero (at most
16 d ahead); a negative sample is refined by 6 bisections and a secant between the last two samples.
With `far` > 0 each step first reads the nearest sample alone (one voxel, `Volume.CLOSEST`): the field
is 1-Lipschitz and the nearest sample lies within half a voxel's diagonal (sqrt 3 / 2), so while that
sample less the half diagonal exceeds `far` the ray steps by it without the trilinear read (8 voxels);
nearer, the step rules above run on trilinear samples, the first of them never stopping a ray alone.

Loop-carried variables are declared as `float(0.0)` / `int(0)`: Warp types a variable reassigned in a
dynamic loop from its constructor, so the literal-only forms ruff prefers would not compile.
"""
# ruff: noqa: UP018, RUF046

from typing import Any

REFINE_ITERATIONS = 6
SECANT_REACH = 16.0


def fill_kernel(wp: Any) -> Any:
    """Store values (V,) float32 at voxels (V, 3) int32 of a volume allocated by tiles."""

    @wp.kernel
    def fill(
        volume: wp.uint64,
        voxels: wp.array(dtype=wp.vec3i),  # type: ignore[valid-type]
        values: wp.array(dtype=float),  # type: ignore[valid-type]
    ) -> None:
        i = wp.tid()
        v = voxels[i]
        wp.volume_store_f(volume, v[0], v[1], v[2], values[i])

    return fill


def march_kernel(wp: Any) -> Any:
    """Depth (P,) meters and steps (P,) of rays (origins in index space, unit directions) through a
    float32 narrow-band volume of distances in meters. `refine` bisections, a secant reach of `reach` d;
    `far` > 0: nearest-sample steps while the nearest sample's bound exceeds `far` voxels (0: trilinear
    samples only)."""

    @wp.kernel
    def march(
        volume: wp.uint64,
        origins: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
        dirs: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
        resolution: float,
        voxel: float,
        horizon: float,
        eps: float,
        slope: float,
        max_steps: int,
        refine: int,
        reach: float,
        far: float,
        depth: wp.array(dtype=float),  # type: ignore[valid-type]
        steps: wp.array(dtype=int),  # type: ignore[valid-type]
    ) -> None:
        i = wp.tid()
        o = origins[i]
        d = dirs[i]
        inv_voxel = 1.0 / voxel
        t0 = float(0.0)
        t1 = horizon * inv_voxel
        for k in range(3):  # clip to the lattice's cube [0, R]^3 (voxels)
            if d[k] != 0.0:
                ta = (0.0 - o[k]) / d[k]
                tb = (resolution - o[k]) / d[k]
                t0 = wp.max(t0, wp.min(ta, tb))
                t1 = wp.min(t1, wp.max(ta, tb))
            elif o[k] < 0.0 or o[k] > resolution:
                t1 = -1.0
        out = float(horizon)
        n = int(0)
        if t0 <= t1:
            t = float(t0)
            prev_t = float(t0)
            prev_d = float(-1.0)
            done = int(0)
            while n < max_steps and done == 0:
                n += 1
                bound = float(0.0)
                if far > 0.0:  # the nearest sample less half a voxel's diagonal bounds the distance here
                    bound = wp.volume_sample_f(volume, o + t * d, wp.Volume.CLOSEST) * inv_voxel - 0.8660254
                f = float(0.0)
                if bound <= far:
                    f = wp.volume_sample_f(volume, o + t * d, wp.Volume.LINEAR) * inv_voxel
                if bound > far:  # far from every surface: step by the nearest sample's bound
                    prev_t = t
                    prev_d = -1.0  # no trilinear sample behind: the next one cannot stop the ray alone
                    t = t + bound
                    if t > t1:
                        done = 2
                elif f < 0.0:  # inside: bisect between the last free sample and here, then a secant
                    lo = float(prev_t)
                    hi = float(t)
                    flo = float(prev_d)
                    fhi = float(f)
                    if prev_d < 0.0:  # no free trilinear sample behind (the first step, or after far steps)
                        lo = t
                        flo = f
                    for _r in range(refine):
                        mid = 0.5 * (lo + hi)
                        fm = wp.volume_sample_f(volume, o + mid * d, wp.Volume.LINEAR) * inv_voxel
                        if fm < 0.0:
                            hi = mid
                            fhi = fm
                        else:
                            lo = mid
                            flo = fm
                    hit = float(lo)
                    if flo - fhi > 0.0:
                        hit = lo + (hi - lo) * (flo / (flo - fhi))
                    out = hit * voxel
                    done = 1
                elif f < eps + slope * t and f <= prev_d:  # near: where the last two samples' line meets 0
                    stop = float(t)
                    if f < prev_d:
                        stop = t + wp.min(f * (t - prev_t) / (prev_d - f), reach * f)
                    out = wp.min(stop, t1) * voxel
                    done = 1
                else:
                    prev_t = t
                    prev_d = f
                    t = t + wp.max(f, eps)
                    if t > t1:
                        done = 2
            if done == 0:
                out = wp.min(t * voxel, horizon)
        depth[i] = out
        steps[i] = n

    return march
