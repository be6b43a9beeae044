"""ctypes mirrors of the launcher argument structs in csrc/launch_args.h (TraceArgs, SampleArgs,
SweepArgs), and the size of the per-actor origin record (OriginSample, csrc/ray_walk.h).

Both launchers (CPU extension and CUDA library) take the address of one of these structs. Each
build reports sizeof() of its structs; `check_layout` compares them with these mirrors at load.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable

ORIGIN_SAMPLE_BYTES = 80
"""sizeof(OriginSample): one actor's origin sample in the launch's origin scratch (csrc/ray_walk.h)."""


class TraceArgs(ctypes.Structure):
    """Arguments of one trace launch (field meanings in csrc/launch_args.h)."""

    _fields_ = [
        ("nodes", ctypes.c_void_p),
        ("grid", ctypes.c_void_p),
        ("bricks", ctypes.c_void_p),
        ("brick_class", ctypes.c_void_p),
        ("scenes", ctypes.c_void_p),
        ("scene_ids", ctypes.c_void_p),
        ("origins", ctypes.c_void_p),
        ("directions", ctypes.c_void_p),
        ("yaw", ctypes.c_void_p),
        ("ray_order", ctypes.c_void_p),
        ("out_depth", ctypes.c_void_p),
        ("out_semantic", ctypes.c_void_p),
        ("out_steps", ctypes.c_void_p),
        ("stream", ctypes.c_void_p),
        ("prims", ctypes.c_void_p),
        ("prim_world", ctypes.c_void_p),
        ("prim_scratch", ctypes.c_void_p),
        ("brick_atlas", ctypes.c_uint64),
        ("num_actors", ctypes.c_int64),
        ("num_rays", ctypes.c_int64),
        ("prim_scratch_bytes", ctypes.c_int64),
        ("num_scenes", ctypes.c_int32),
        ("scene_id_bytes", ctypes.c_int32),
        ("semantic_bytes", ctypes.c_int32),
        ("directions_shared", ctypes.c_int32),
        ("max_steps", ctypes.c_int32),
        ("cpu_threads", ctypes.c_int32),
        ("device", ctypes.c_int32),
        ("horizon", ctypes.c_float),
        ("hit_epsilon", ctypes.c_float),
        ("prims_per_world", ctypes.c_int32),
        ("num_worlds", ctypes.c_int32),
        ("hit_slope", ctypes.c_float),
        ("atlas_shift", ctypes.c_int32),
        ("origin_scratch", ctypes.c_void_p),
    ]


class SampleArgs(ctypes.Structure):
    """Arguments of one point-query launch (field meanings in csrc/launch_args.h)."""

    _fields_ = [
        ("nodes", ctypes.c_void_p),
        ("grid", ctypes.c_void_p),
        ("bricks", ctypes.c_void_p),
        ("scenes", ctypes.c_void_p),
        ("scene_ids", ctypes.c_void_p),
        ("points", ctypes.c_void_p),
        ("out_distance", ctypes.c_void_p),
        ("stream", ctypes.c_void_p),
        ("prims", ctypes.c_void_p),
        ("prim_world", ctypes.c_void_p),
        ("prim_owner", ctypes.c_void_p),
        ("brick_atlas", ctypes.c_uint64),
        ("num_points", ctypes.c_int64),
        ("num_scenes", ctypes.c_int32),
        ("scene_id_bytes", ctypes.c_int32),
        ("cpu_threads", ctypes.c_int32),
        ("device", ctypes.c_int32),
        ("prims_per_world", ctypes.c_int32),
        ("num_worlds", ctypes.c_int32),
        ("atlas_shift", ctypes.c_int32),
    ]


class SweepArgs(ctypes.Structure):
    """Arguments of one obstacle-sweep launch (field meanings in csrc/launch_args.h)."""

    _fields_ = [
        ("prims", ctypes.c_void_p),
        ("delta", ctypes.c_void_p),
        ("drone", ctypes.c_void_p),
        ("out_t", ctypes.c_void_p),
        ("out_distance", ctypes.c_void_p),
        ("stream", ctypes.c_void_p),
        ("num_items", ctypes.c_int64),
        ("prims_per_actor", ctypes.c_int32),
        ("iterations", ctypes.c_int32),
        ("cpu_threads", ctypes.c_int32),
        ("device", ctypes.c_int32),
        ("radius", ctypes.c_float),
        ("skin", ctypes.c_float),
    ]


def check_layout(
    trace_size: Callable[[], int],
    sample_size: Callable[[], int],
    sweep_size: Callable[[], int],
    origin_size: Callable[[], int],
    where: str,
) -> None:
    """Raise RuntimeError when a build's struct sizes disagree with these mirrors (a stale build)."""
    for name, got, want in (
        ("TraceArgs", trace_size(), ctypes.sizeof(TraceArgs)),
        ("SampleArgs", sample_size(), ctypes.sizeof(SampleArgs)),
        ("SweepArgs", sweep_size(), ctypes.sizeof(SweepArgs)),
        ("OriginSample", origin_size(), ORIGIN_SAMPLE_BYTES),
    ):
        if got != want:
            raise RuntimeError(
                f"{where}: sizeof({name}) is {got} bytes, navi_env.tracer.abi expects {want}; rebuild navi_env"
            )
