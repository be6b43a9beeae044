"""The Warp kernels of `navi bench trace --vs-warp`: the BVH ray cast and the obstacles' vertex shift.

Kept in its own module without `from __future__ import annotations`: Warp reads the kernel's
annotations as types, and older releases (warp-lang 1.0.x, the anchor's version) cannot resolve
string annotations.
"""

from typing import Any


def ray_kernel(wp: Any) -> Any:
    """The Warp kernel: first hit distance along each ray, `horizon` on a miss."""

    @wp.kernel
    def cast(
        mesh: wp.uint64,
        origins: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
        dirs: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
        horizon: float,
        depth: wp.array(dtype=float),  # type: ignore[valid-type]
    ) -> None:
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, origins[i], dirs[i], horizon)
        if q.result:
            depth[i] = q.t
        else:
            depth[i] = horizon

    return cast


def shift_kernel(wp: Any) -> Any:
    """The Warp kernel that moves the obstacle vertices (points[first:]) by step[0]."""

    @wp.kernel
    def shift(
        points: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
        first: int,
        step: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    ) -> None:
        i = wp.tid()
        points[first + i] = points[first + i] + step[0]

    return shift
