"""Batched sphere tracing of a SceneCorpus: validation, then one launch (CPU threads or CUDA).

`trace` reads and writes the tensors in place through their data pointers: no staging, no copies.
With `skip_direction_validation=True` it never synchronises with the device; otherwise one
device-to-host read checks direction norms and scene ids together. Contract in docs/SDFDAG_RUNTIME.md.

Shapes: B actors (batch), R rays per actor, N query points.
"""

from __future__ import annotations

import ctypes
import functools
import importlib
from dataclasses import dataclass
from types import ModuleType

import numpy as np
import torch

from navi_env.tracer.abi import ORIGIN_SAMPLE_BYTES, SampleArgs, SweepArgs, TraceArgs, check_layout
from navi_env.tracer.primitives import check_prims
from navi_env.tracer.scene import SceneCorpus

DEFAULT_MAX_STEPS = 256  # main-loop samples per ray
DEFAULT_HORIZON = 100.0  # meters
DEFAULT_HIT_EPSILON_VOXELS = 0.1  # used per scene when hit_epsilon is None (kDefaultHitEpsilonVoxels)
NORM_TOLERANCE = 1e-3  # | |direction| - 1 | allowed
RAY_GROUP = 128  # work items per ray group (kRayGroup in csrc/primitives.h)
MASK_PRIMS = 64  # most primitives per world with per-group masks (kMaskPrims)


def prim_scratch_bytes(batch: int, rays: int, per_world: int, shared: bool) -> int:
    """Device bytes a trace launch with primitives builds its tables in (csrc/primitives.h,
    prim_scratch_bytes): cull entries (B, K) of 16 bytes, and with shared directions and K <= 64 also
    a cone per ray group (G,) of 16 bytes and a mask word per actor and group (B, G) of 8 bytes."""
    groups = -(-rays // RAY_GROUP)
    table = batch * per_world * 16
    return groups * 16 + table + batch * groups * 8 if shared and per_world <= MASK_PRIMS else table


@dataclass(frozen=True)
class TraceParams:
    """Validated scalar parameters of one trace call."""

    batch: int  # B
    rays: int  # R
    shared: bool  # directions (R, 3) shared by all actors
    max_steps: int
    horizon: float  # meters
    hit_epsilon: float  # meters, or -1.0 for the per-scene default
    hit_slope: float  # >= 0: the threshold at distance t is hit_epsilon + hit_slope * t


def _fail_type(name: str, want: str, t: torch.Tensor) -> TypeError:
    return TypeError(f"{name} must be {want}, got {t.dtype}")


def _check_tensor(name: str, t: object, device: torch.device) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.device != device:
        raise ValueError(f"{name} is on {t.device} but the scenes are on {device}")
    if not t.is_contiguous():
        raise ValueError(f"{name} must be contiguous")
    return t


def _check_float(name: str, t: torch.Tensor, shape: tuple[int, ...]) -> None:
    if t.dtype != torch.float32:
        raise _fail_type(name, "float32", t)
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")


def _check_scene_ids(scene_ids: torch.Tensor, dev: torch.device, letter: str) -> int:
    """scene_ids must be a 1-d int32/int64 tensor on `dev`; returns its length."""
    scene_ids = _check_tensor("scene_ids", scene_ids, dev)
    if scene_ids.dtype not in (torch.int32, torch.int64):
        raise _fail_type("scene_ids", "int32 or int64", scene_ids)
    if scene_ids.dim() != 1:
        raise ValueError(f"scene_ids must be ({letter},), got shape {tuple(scene_ids.shape)}")
    return int(scene_ids.shape[0])


def validate_trace(
    scenes: SceneCorpus,
    scene_ids: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    out_depth: torch.Tensor,
    out_semantic: torch.Tensor | None,
    yaw: torch.Tensor | None,
    out_steps: torch.Tensor | None,
    ray_order: torch.Tensor | None,
    max_steps: int,
    horizon: float,
    hit_epsilon: float | None,
    skip_direction_validation: bool,
    hit_slope: float = 0.0,
) -> TraceParams:
    """Check every argument of `trace`; raise TypeError/ValueError with the reason. Returns the shape."""
    if not isinstance(scenes, SceneCorpus):
        raise TypeError(f"scenes must be a SceneCorpus, got {type(scenes).__name__}")
    dev = scenes.device
    _check_atlas(scenes)
    b = _check_scene_ids(scene_ids, dev, "B")
    origins = _check_tensor("origins", origins, dev)
    directions = _check_tensor("directions", directions, dev)
    out_depth = _check_tensor("out_depth", out_depth, dev)
    _check_float("origins", origins, (b, 3))
    if directions.dim() == 2:
        r, shared = directions.shape[0], True
        _check_float("directions", directions, (r, 3))
    elif directions.dim() == 3:
        r, shared = directions.shape[1], False
        _check_float("directions", directions, (b, r, 3))
    else:
        raise ValueError(f"directions must be (R, 3) or (B, R, 3), got shape {tuple(directions.shape)}")
    _check_float("out_depth", out_depth, (b, r))
    if yaw is not None:
        _check_float("yaw", _check_tensor("yaw", yaw, dev), (b,))
    if out_semantic is not None:
        out_semantic = _check_tensor("out_semantic", out_semantic, dev)
        if out_semantic.dtype not in (torch.int32, torch.uint8):
            raise _fail_type("out_semantic", "int32 or uint8", out_semantic)
        if tuple(out_semantic.shape) != (b, r):
            raise ValueError(f"out_semantic must have shape {(b, r)}, got {tuple(out_semantic.shape)}")
    if ray_order is not None:
        ray_order = _check_tensor("ray_order", ray_order, dev)
        if ray_order.dtype != torch.int32:
            raise _fail_type("ray_order", "int32", ray_order)
        if tuple(ray_order.shape) != (r,):
            raise ValueError(f"ray_order must have shape {(r,)}, got {tuple(ray_order.shape)}")
    if out_steps is not None:
        out_steps = _check_tensor("out_steps", out_steps, dev)
        if out_steps.dtype != torch.int32:
            raise _fail_type("out_steps", "int32", out_steps)
        if tuple(out_steps.shape) != (b, r):
            raise ValueError(f"out_steps must have shape {(b, r)}, got {tuple(out_steps.shape)}")
    if not 1 <= max_steps <= 2**31 - 1:
        raise ValueError(f"max_steps must be in [1, 2^31 - 1], got {max_steps}")
    if not (0.0 < horizon < float("inf")):
        raise ValueError(f"horizon must be a positive finite number of meters, got {horizon}")
    if hit_epsilon is not None and not (0.0 < hit_epsilon < float("inf")):
        raise ValueError(f"hit_epsilon must be positive and finite (meters) or None, got {hit_epsilon}")
    if not 0.0 <= hit_slope < 1.0:
        raise ValueError(
            f"hit_slope must be in [0, 1) (meters of threshold per meter of ray), got {hit_slope}"
        )
    if not skip_direction_validation:
        _check_values(scenes, scene_ids, directions, ray_order)
    return TraceParams(
        batch=b,
        rays=r,
        shared=shared,
        max_steps=int(max_steps),
        horizon=float(horizon),
        hit_epsilon=-1.0 if hit_epsilon is None else float(hit_epsilon),
        hit_slope=float(hit_slope),
    )


def _check_values(
    scenes: SceneCorpus, scene_ids: torch.Tensor, directions: torch.Tensor, ray_order: torch.Tensor | None
) -> None:
    """Direction norms, scene-id range and ray_order being a permutation: numpy on the CPU, one
    device-to-host read on CUDA."""
    lo, hi = (1.0 - NORM_TOLERANCE) ** 2, (1.0 + NORM_TOLERANCE) ** 2  # bounds of |d|^2
    r = directions.shape[-2]
    if directions.device.type == "cpu":
        x = directions.reshape(-1, 3).numpy()  # (R or B*R, 3) float32, shares memory
        norm2 = np.einsum("ij,ij->i", x, x)  # (R or B*R,) float32
        dirs_ok = bool(((norm2 >= lo) & (norm2 <= hi)).all())
        ids = scene_ids.numpy()  # (B,)
        ids_ok = bool(((ids >= 0) & (ids < len(scenes))).all())
        order_ok = ray_order is None or bool(np.array_equal(np.sort(ray_order.numpy()), np.arange(r)))
    else:
        dirs = directions.reshape(-1, 3)  # (R or B*R, 3)
        norm2 = (dirs * dirs).sum(dim=1)  # (R or B*R,)
        checks = [((norm2 >= lo) & (norm2 <= hi)).all(), ((scene_ids >= 0) & (scene_ids < len(scenes))).all()]
        if ray_order is not None:
            in_range = ((ray_order >= 0) & (ray_order < r)).all()  # () bool
            counts = torch.bincount(ray_order.clamp(0, max(r - 1, 0)).long(), minlength=r)  # (R,)
            checks.append(in_range & (counts == 1).all())
        flags = torch.stack(checks).cpu()  # (2 or 3,) bool, the one sync
        dirs_ok, ids_ok = bool(flags[0]), bool(flags[1])
        order_ok = ray_order is None or bool(flags[2])
    if not ids_ok:
        raise ValueError(f"scene_ids must lie in [0, {len(scenes)})")
    if not dirs_ok:
        raise ValueError(
            f"directions must be unit vectors (| |d| - 1 | <= {NORM_TOLERANCE}); "
            "found a zero-length, NaN, infinite or unnormalised direction"
        )
    if not order_ok:
        raise ValueError(f"ray_order must be a permutation of 0..{r - 1}")


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


@functools.cache
def cpu_launcher() -> ModuleType:
    """The CPU extension built at install (navi_env.tracer._trace_cpu), layout-checked once."""
    _trace_cpu = importlib.import_module("navi_env.tracer._trace_cpu")
    check_layout(
        _trace_cpu.trace_args_size,
        _trace_cpu.sample_args_size,
        _trace_cpu.sweep_args_size,
        _trace_cpu.origin_sample_size,
        "navi_env.tracer._trace_cpu",
    )
    return _trace_cpu


def _stream(device: torch.device) -> int:
    return int(torch.cuda.current_stream(device).cuda_stream)


def _device_index(device: torch.device) -> int:
    return device.index if device.index is not None else torch.cuda.current_device()


def _cuda_check(code: int) -> None:
    if code != 0:
        from navi_env.tracer.cuda_build import cuda_library

        message = cuda_library().navi_cuda_error_string(code).decode()
        raise RuntimeError(f"CUDA tracer launch failed: {message} (code {code})")


def launch(stage: str, args: TraceArgs | SampleArgs | SweepArgs, device: torch.device) -> None:
    """Run one filled argument struct on the CPU launcher or the CUDA launcher of `stage` (trace,
    sample or sweep)."""
    if device.type == "cpu":
        args.cpu_threads = torch.get_num_threads()
        code = getattr(cpu_launcher(), stage)(ctypes.addressof(args))
        if code != 0:
            why = {1: "a worker thread did not start", 2: "the primitive scratch is missing or too small"}
            raise RuntimeError(f"CPU {stage} launcher failed: {why.get(code, 'unknown error')} (code {code})")
    elif device.type == "cuda":
        from navi_env.tracer.cuda_build import cuda_library

        args.stream = _stream(device)
        args.device = _device_index(device)
        _cuda_check(getattr(cuda_library(), f"navi_{stage}_cuda")(ctypes.addressof(args)))
    else:
        raise ValueError(f"the {stage} launcher runs on cpu or cuda devices, not {device}")


_ORIGIN_PASS = True
"""Sample each actor's origin once before its rays (the launch). False samples every ray's origin in
the ray itself: the slow twin the origin-sample parity tests compare the launch with (results, steps
included, are the same bit for bit); only those tests set it."""


def trace(
    scenes: SceneCorpus,
    scene_ids: torch.Tensor,
    origins: torch.Tensor,
    directions: torch.Tensor,
    *,
    out_depth: torch.Tensor,
    out_semantic: torch.Tensor | None = None,
    yaw: torch.Tensor | None = None,
    out_steps: torch.Tensor | None = None,
    ray_order: torch.Tensor | None = None,
    max_steps: int = DEFAULT_MAX_STEPS,
    horizon: float = DEFAULT_HORIZON,
    hit_epsilon: float | None = None,
    skip_direction_validation: bool = False,
    prims: torch.Tensor | None = None,
    prim_world: torch.Tensor | None = None,
    hit_slope: float = 0.0,
) -> None:
    """Sphere-trace B actors x R rays; write depth (meters), semantic and step counts in place.

    scenes: the resident corpus; scene_ids: (B,) int32/int64 scene of each actor.
    origins: (B, 3) float32 world meters. directions: (R, 3) shared or (B, R, 3) per actor, float32
    unit vectors, rotated about +Z by yaw (B,) float32 radians when given.
    out_depth: (B, R) float32 meters, `horizon` on a miss. out_semantic: (B, R) int32 or uint8,
    0 = miss, 1 + class id on a hit (uint8 saturates at 255). out_steps: (B, R) int32 main-loop steps.
    ray_order: (R,) int32 permutation deciding which rays share a GPU warp (e.g.
    `navi_env.rays.tiled_ray_order`); results do not depend on it, speed does (coherent warps).
    Without validation a non-permutation leaves some outputs unwritten (never out of bounds).
    max_steps: bound per ray; a ray out of steps reports the distance reached and semantic 0.
    hit_epsilon: meters; None uses 0.1 voxel of each scene. hit_slope: the hit threshold grows with
    the distance t travelled, hit_epsilon + hit_slope * t (0: a fixed threshold); a ray stopped
    within it reports where the line through its last two samples meets the surface (at most 16
    times its last distance ahead). skip_direction_validation: skip the
    norm and scene-id checks (and their device sync); an out-of-range id then yields NaN depth.
    prims: (W, K, 16) float32 dynamic primitive records (navi_env.tracer.primitives); prim_world: (B,) int32
    world of each actor (default: actor b sees world b). A ray reports the first primitive it enters
    when that comes before the static surface; actor b never sees the primitive it owns.
    The launch samples each actor's origin once before its rays: every ray whose origin lies in the cube
    takes its first sample there.
    """
    p = validate_trace(
        scenes, scene_ids, origins, directions, out_depth, out_semantic, yaw, out_steps, ray_order,
        max_steps, horizon, hit_epsilon, skip_direction_validation, hit_slope,
    )  # fmt: skip
    worlds, per_world = check_prims(prims, prim_world, p.batch, scenes.device, "one per actor")
    scratch = None
    if prims is not None and per_world > 0:
        # the launch's primitive tables, rebuilt by every launch (the caching allocator makes this free,
        # and a buffer per call stays correct when calls overlap on several streams)
        nbytes = prim_scratch_bytes(p.batch, p.rays, per_world, p.shared)
        scratch = torch.empty(nbytes, dtype=torch.uint8, device=scenes.device)  # (bytes,)
    origin = None
    if _ORIGIN_PASS and p.batch * p.rays > 0:
        # the launch's origin samples: like the primitive tables a fresh buffer per call (free from the
        # caching allocator, private to a CUDA graph's pool, correct when calls overlap on streams)
        nbytes = p.batch * ORIGIN_SAMPLE_BYTES
        origin = torch.empty(nbytes, dtype=torch.uint8, device=scenes.device)  # (B * 80,) OriginSample
    args = TraceArgs(
        nodes=scenes.nodes.data_ptr(),
        grid=scenes.grid.data_ptr(),
        bricks=scenes.bricks.data_ptr(),
        brick_class=scenes.brick_class.data_ptr(),
        scenes=scenes.table.data_ptr(),
        scene_ids=scene_ids.data_ptr(),
        origins=origins.data_ptr(),
        directions=directions.data_ptr(),
        yaw=_ptr(yaw),
        ray_order=_ptr(ray_order),
        out_depth=out_depth.data_ptr(),
        out_semantic=_ptr(out_semantic),
        out_steps=_ptr(out_steps),
        num_actors=p.batch,
        num_rays=p.rays,
        num_scenes=len(scenes),
        scene_id_bytes=scene_ids.element_size(),
        semantic_bytes=0 if out_semantic is None else out_semantic.element_size(),
        directions_shared=int(p.shared),
        max_steps=p.max_steps,
        horizon=p.horizon,
        hit_epsilon=p.hit_epsilon,
        hit_slope=p.hit_slope,
        prims=_ptr(prims),
        prim_world=_ptr(prim_world),
        prims_per_world=per_world,
        num_worlds=worlds,
        prim_scratch=_ptr(scratch),
        prim_scratch_bytes=0 if scratch is None else scratch.numel(),
        brick_atlas=_atlas(scenes)[0],
        atlas_shift=_atlas(scenes)[1],
        origin_scratch=_ptr(origin),
    )
    if p.batch * p.rays > 0:
        launch("trace", args, scenes.device)


def validate_sample(
    scenes: SceneCorpus,
    scene_ids: torch.Tensor,
    points: torch.Tensor,
    out: torch.Tensor | None,
    prims: torch.Tensor | None = None,
    prim_world: torch.Tensor | None = None,
    prim_owner: torch.Tensor | None = None,
) -> tuple[int, int, int]:
    """Check the arguments of `sample_distance`; returns (N, W, K) (W = K = 0 without prims)."""
    if not isinstance(scenes, SceneCorpus):
        raise TypeError(f"scenes must be a SceneCorpus, got {type(scenes).__name__}")
    dev = scenes.device
    _check_atlas(scenes)
    n = _check_scene_ids(scene_ids, dev, "N")
    points = _check_tensor("points", points, dev)
    _check_float("points", points, (n, 3))
    if out is not None:
        _check_float("out", _check_tensor("out", out, dev), (n,))
    worlds, per_world = check_prims(prims, prim_world, n, dev, "one per point")
    if prims is not None and prim_world is None:
        raise ValueError("sample_distance with prims needs prim_world (N,) int32")
    if prim_owner is not None:
        check_prims(prims, prim_owner, n, dev, "prim_owner: one per point")
    return n, worlds, per_world


def sample_distance(
    scenes: SceneCorpus,
    scene_ids: torch.Tensor,
    points: torch.Tensor,
    out: torch.Tensor | None = None,
    *,
    prims: torch.Tensor | None = None,
    prim_world: torch.Tensor | None = None,
    prim_owner: torch.Tensor | None = None,
) -> torch.Tensor:
    """Signed distance in meters at N points: (N,) float32 (written into `out` when given).

    Trilinear inside bricks, the signed lower bound inside far cubes, the (positive) distance to the
    cube outside it; NaN for an out-of-range scene id (not checked here: no device sync). With
    prims (W, K, 16) and prim_world (N,) int32: the min with every primitive of the point's world,
    leaving out the primitive owned by prim_owner (N,) int32 (a drone's own sphere) when given.
    """
    n = validate_sample(scenes, scene_ids, points, out, prims, prim_world, prim_owner)[0]
    buffers = (scenes.nodes, scenes.grid, scenes.bricks, scenes.table)
    atlas, shift = _atlas(scenes)
    if out is None and torch.compiler.is_compiling():  # an opaque op in a compiled graph (see _sample_op)
        return _sample_op(*buffers, atlas, shift, scene_ids, points, prims, prim_world, prim_owner)
    result = torch.empty(n, dtype=torch.float32, device=scenes.device) if out is None else out  # (N,) float32
    _launch_sample(*buffers, atlas, shift, scene_ids, points, result, prims, prim_world, prim_owner)
    return result


def _check_atlas(scenes: SceneCorpus) -> None:
    """A CUDA corpus reads its bricks from its atlas, on its own device; a CPU corpus has none."""
    dev = scenes.device
    if dev.type == "cuda" and (
        scenes.atlas is None
        or scenes.atlas.device.index != (dev.index if dev.index is not None else torch.cuda.current_device())
    ):
        raise ValueError(
            f"a corpus on {dev} needs its brick atlas there: load it with load_corpus(..., device)"
        )
    if dev.type != "cuda" and scenes.atlas is not None:
        raise ValueError(f"a corpus on {dev} reads corner words; its brick atlas belongs to a CUDA corpus")


def _atlas(scenes: SceneCorpus) -> tuple[int, int]:
    """(texture object, p) of a CUDA corpus' brick atlas; (0, 0) on the CPU, which reads corner words."""
    return (0, 0) if scenes.atlas is None else (scenes.atlas.texture, scenes.atlas.shift)


def _launch_sample(
    nodes: torch.Tensor,
    grid: torch.Tensor,
    bricks: torch.Tensor,
    table: torch.Tensor,
    atlas: int,
    atlas_shift: int,
    scene_ids: torch.Tensor,
    points: torch.Tensor,
    result: torch.Tensor,
    prims: torch.Tensor | None,
    prim_world: torch.Tensor | None,
    prim_owner: torch.Tensor | None,
) -> None:
    """The sample launch over validated arguments: a SceneCorpus' buffers, N points, result (N,)."""
    n = points.shape[0]
    if n == 0:
        return
    worlds, per_world = (0, 0) if prims is None else (int(prims.shape[0]), int(prims.shape[1]))
    args = SampleArgs(
        nodes=nodes.data_ptr(),
        grid=grid.data_ptr(),
        bricks=bricks.data_ptr(),
        scenes=table.data_ptr(),
        scene_ids=scene_ids.data_ptr(),
        points=points.data_ptr(),
        out_distance=result.data_ptr(),
        prims=_ptr(prims),
        prim_world=_ptr(prim_world),
        prim_owner=_ptr(prim_owner),
        num_points=n,
        num_scenes=table.shape[0],
        scene_id_bytes=scene_ids.element_size(),
        prims_per_world=per_world,
        num_worlds=worlds,
        brick_atlas=atlas,
        atlas_shift=atlas_shift,
    )
    launch("sample", args, points.device)


@torch.library.custom_op("navi::sample_distance", mutates_args=())
def _sample_op(
    nodes: torch.Tensor,
    grid: torch.Tensor,
    bricks: torch.Tensor,
    table: torch.Tensor,
    atlas: int,
    atlas_shift: int,
    scene_ids: torch.Tensor,
    points: torch.Tensor,
    prims: torch.Tensor | None,
    prim_world: torch.Tensor | None,
    prim_owner: torch.Tensor | None,
) -> torch.Tensor:
    """sample_distance as an op torch.compile keeps whole (arguments validated by the caller): the
    distance (N,) float32 at points (N, 3), so the elementwise work around it fuses into few kernels."""
    result = torch.empty(points.shape[0], dtype=torch.float32, device=points.device)  # (N,) float32
    _launch_sample(nodes, grid, bricks, table, atlas, atlas_shift, scene_ids, points, result, prims, prim_world,
                   prim_owner)  # fmt: skip
    return result


@_sample_op.register_fake
def _(
    nodes: torch.Tensor,
    grid: torch.Tensor,
    bricks: torch.Tensor,
    table: torch.Tensor,
    atlas: int,
    atlas_shift: int,
    scene_ids: torch.Tensor,
    points: torch.Tensor,
    prims: torch.Tensor | None,
    prim_world: torch.Tensor | None,
    prim_owner: torch.Tensor | None,
) -> torch.Tensor:
    return points.new_empty(points.shape[0])  # (N,) float32


def sweep_prims(
    prims: torch.Tensor, delta: torch.Tensor, drone: torch.Tensor, radius: float, skin: float, iterations: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The obstacle sweep in one launch (csrc/queries.h `sweep_item`; torch twin
    navi_env.sim.obstacles.sweep_ref): for N actors' K primitives, records prims (N, K, 16) translating
    by delta (N, K, 3) towards a drone sphere of `radius` at drone (N, 3), the fraction t (N, K) in
    [0, 1] each may move while keeping `skin` outside the sphere (`iterations` march steps), and its
    distance from the drone centre there (N, K) (+inf for an empty slot). No host sync."""
    dev = prims.device
    if prims.dim() != 3 or prims.shape[2] != 16 or prims.dtype != torch.float32:
        raise ValueError(f"prims must be (N, K, 16) float32, got {tuple(prims.shape)} {prims.dtype}")
    n, k = int(prims.shape[0]), int(prims.shape[1])
    for name, t, shape in (("delta", delta, (n, k, 3)), ("drone", drone, (n, 3))):
        _check_float(name, _check_tensor(name, t, dev), shape)
    _check_tensor("prims", prims, dev)
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    out_t = torch.empty(n, k, dtype=torch.float32, device=dev)  # (N, K)
    out_distance = torch.empty(n, k, dtype=torch.float32, device=dev)  # (N, K) m
    if n * k == 0:
        return out_t, out_distance
    args = SweepArgs(
        prims=prims.data_ptr(),
        delta=delta.data_ptr(),
        drone=drone.data_ptr(),
        out_t=out_t.data_ptr(),
        out_distance=out_distance.data_ptr(),
        num_items=n * k,
        prims_per_actor=k,
        iterations=iterations,
        radius=radius,
        skin=skin,
    )
    launch("sweep", args, dev)
    return out_t, out_distance
