"""The encoder's input stage: observations -> patch tokens (N, P, 4·pa·pe), the rows the encoder's
linear patch embedding reads.

An observation (N, 3, Az, El) (depth / horizon, semantic, delta depth) becomes, per ray, four values: the
log-depth `near_field`, then its three channels, after the view cap (`cap_view`) where the encoder's
view range is below 1. `patchify` lays them out as non-overlapping pa × pe patches, azimuth-major. The
update hands the encoder its minibatch still compact (`CompactFrames`: the rollout's float16 depth and
semantic bytes, 3 bytes per ray), decoded as `gather_frames` does.

`patch_tokens` is the stage. On a CPU it runs `patch_tokens_ref` (the decode, the cap, the near field and
the patch layout written out in torch). On CUDA one Triton program per (sample, patch) reads the patch's
rays once, float32 frames or compact ones, and writes their four values in the dtype the embedding
multiplies in (bf16 under amp). Compiled by inductor, the stage was one pass that computed each output
element on its own, so each ray's gather and decode ran once for each of its four values
(docs/PERFORMANCE.md). The kernel makes the same float32 operations in the same order; its log is the
GPU's fast log, as in inductor's code, so its float32 tokens lie within 1e-6 of the twin's and its bf16
tokens within one unit in the last place, nearly all equal (tests/learner/test_learner_tokens.py, and
the CUDA check in test_learner_gpu.py).

Legend: N samples, C channels, Az × El rays, pa × pe patch, P patches, T rollout steps, L sequence
length, M sequences (N = L·M in the update).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from navi_env.sim.observation import unpack

try:  # the kernel needs Triton (it comes with torch's CUDA builds); without it the CPU twin serves
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - every torch build with CUDA ships Triton
    triton = None


def patchify(obs: torch.Tensor, patch: int | tuple[int, int]) -> torch.Tensor:
    """(N, C, Az, El) -> (N, Az/pa · El/pe, C·pa·pe) tokens, azimuth-major (patch = pa or (pa, pe))."""
    pa, pe = (patch, patch) if isinstance(patch, int) else patch
    n, c, az, el = obs.shape
    x = obs.reshape(n, c, az // pa, pa, el // pe, pe)  # (N, C, Pa, pa, Pe, pe)
    x = x.permute(0, 2, 4, 1, 3, 5)  # (N, Pa, Pe, C, pa, pe)
    return x.reshape(n, (az // pa) * (el // pe), c * pa * pe)  # (N, P, C·pa·pe)


NEAR_FIELD_EPS = 1e-3
"""Depth (as a fraction of the horizon) below which near_field saturates at 1."""


def near_field(depth: torch.Tensor) -> torch.Tensor:
    """log(depth + eps) / log(eps) of normalised depth (any shape) in [0, 1]: 1 at contact, 0 at the horizon."""
    return torch.log(depth.clamp(0.0, 1.0) + NEAR_FIELD_EPS) * (1.0 / math.log(NEAR_FIELD_EPS))


def with_near_field(obs: torch.Tensor) -> torch.Tensor:
    """obs (N, 3, Az, El) -> (N, 4, Az, El) float32: near_field of channel 0, then the three channels."""
    x = obs.float()  # (N, 3, Az, El)
    return torch.cat([near_field(x[:, :1]), x], dim=1)  # (N, 4, Az, El)


def cap_view(obs: torch.Tensor, view_range: float) -> torch.Tensor:
    """obs (N, 3, Az, El) as an encoder with EngineConfig.view_range reads it, (N, 3, Az, El) float32:
    depth beyond `view_range` (a fraction of the horizon; a miss reads 1) is `view_range`, the semantic
    channel there the unknown class (0.5) unless a goal mark (< 0) is painted on the ray, and delta depth
    the difference of the capped frames (the previous frame's depth is depth - delta, exactly; with
    `view_range` a float16 value, as the encoder rounds it, the capped delta is exact too)."""
    depth, semantic, delta = obs.float().unbind(1)  # (N, Az, El) each
    capped = depth.clamp(max=view_range)  # (N, Az, El)
    before = (depth - delta).clamp(max=view_range)  # (N, Az, El) the previous frame's depth, capped
    unknown = (depth > view_range) & (semantic >= 0.0)  # (N, Az, El) bool: far, no goal mark
    semantic = torch.where(unknown, 0.5, semantic)  # (N, Az, El)
    delta = capped - before  # (N, Az, El)
    return torch.stack([capped, semantic, delta], dim=1)  # (N, 3, Az, El)


class CompactFrames(NamedTuple):
    """A minibatch's observations as compact storage holds them (gather_frames gives the float32 frames)."""

    depth16: torch.Tensor  # (T+1, N, Az, El) float16, the whole rollout's channel 0
    semantic: torch.Tensor  # (T, N, Az, El) uint8, the whole rollout's semantic codes
    resets: torch.Tensor  # (L, M) bool, the sequences' episode starts
    table: torch.Tensor  # (256,) float32 semantic code -> channel 1
    chunks: torch.Tensor  # (M,) int64 BPTT chunk of each sequence
    actors: torch.Tensor  # (M,) int64 actor of each sequence
    chunk: int  # L


def sequences(buf: torch.Tensor, chunks: torch.Tensor, actors: torch.Tensor, chunk: int) -> torch.Tensor:
    """The whole BPTT sequences (chunk c, actor a) of a (T, N, ...) buffer -> (L, M, ...), time-major."""
    view = buf.view(buf.shape[0] // chunk, chunk, *buf.shape[1:])  # (T/L, L, N, ...)
    return view[chunks, :, actors].transpose(0, 1)  # (L, M, ...)


def gather_frames(
    depth16: torch.Tensor,
    semantic: torch.Tensor,
    resets: torch.Tensor,
    table: torch.Tensor,
    chunks: torch.Tensor,
    actors: torch.Tensor,
    chunk: int,
) -> torch.Tensor:
    """The observations (L, M, 3, Az, El) float32 of the sequences (chunk c, actor a) from compact storage:
    depth16 (T+1, N, Az, El) float16 from the frame before the rollout, semantic (T, N, Az, El) uint8,
    the sequences' resets (L, M) bool. Bit-identical to the frames the policy acted on."""
    steps = torch.arange(chunk + 1, device=chunks.device)[:, None]  # (L+1, 1) int64
    frames = chunks[None] * chunk + steps  # (L+1, M) from the frame before each sequence
    depth = depth16[frames, actors[None]]  # (L+1, M, Az, El) float16
    return unpack(depth, sequences(semantic, chunks, actors, chunk), resets, table)  # (L, M, 3, Az, El)


def patch_tokens_ref(obs: torch.Tensor, patch: tuple[int, int], view_range: float) -> torch.Tensor:
    """obs (N, 3, Az, El) -> patch tokens (N, P, 4·pa·pe) float32, written out: the view cap where
    0 < view_range < 1, the near field, the patch layout."""
    if 0.0 < view_range < 1.0:
        obs = cap_view(obs, view_range)  # (N, 3, Az, El) float32
    return patchify(with_near_field(obs), patch)  # (N, P, 4·pa·pe)


def _token_shape(az: int, el: int, pa: int, pe: int) -> tuple[int, int]:
    """(P, 4·pa·pe) for an Az × El view in pa × pe patches; ValueError where a side does not divide."""
    if az % pa or el % pe:
        raise ValueError(f"observation {az}x{el} is not divisible by the {pa}x{pe} patch")
    return (az // pa) * (el // pe), 4 * pa * pe


if triton is not None:

    @triton.jit
    def _patch_tokens_kernel(  # type: ignore[no-untyped-def]
        OUT, OBS, s_n, s_c, s_a, s_e, DEPTH, SEM, RESETS, TABLE, CHUNKS, ACTORS, M, L, NA, AZEL,
        view_range, eps, inv_log_eps, EL: tl.constexpr, EL_PATCHES: tl.constexpr, PA: tl.constexpr,
        PE: tl.constexpr, BLOCK_A: tl.constexpr, BLOCK_E: tl.constexpr, COMPACT: tl.constexpr,
        CAP: tl.constexpr,
    ):  # fmt: skip
        """Program (n, p): patch p of sample n, written to OUT[n, p] (4·PA·PE,). Float32 frames: OBS
        (N, 3, Az, El) with strides s_*. COMPACT: sample n = l·M + m is step l of sequence m, read from
        DEPTH (T+1, NA, Az, El) float16 and SEM (T, NA, Az, El) uint8 (AZEL = Az·El), RESETS (L, M)
        uint8, TABLE (256,) float32, CHUNKS and ACTORS (M,) int64. CAP: cap the view at view_range."""
        n = tl.program_id(0).to(tl.int64)
        p = tl.program_id(1)
        ia = tl.arange(0, BLOCK_A)[:, None]  # (BLOCK_A, 1) azimuth within the patch
        je = tl.arange(0, BLOCK_E)[None, :]  # (1, BLOCK_E) elevation within the patch
        inside = (ia < PA) & (je < PE)  # (BLOCK_A, BLOCK_E)
        az = (p // EL_PATCHES) * PA + ia  # (BLOCK_A, 1)
        el = (p % EL_PATCHES) * PE + je  # (1, BLOCK_E)
        if COMPACT:
            m = n % M
            frame = tl.load(CHUNKS + m) * L + n // M  # the step's frame of the rollout (int64)
            at = (frame * NA + tl.load(ACTORS + m)) * AZEL + az * EL + el  # (BLOCK_A, BLOCK_E) int64
            prev = tl.load(DEPTH + at, mask=inside, other=0.0).to(tl.float32)  # the frame before
            now = tl.load(DEPTH + at + NA * AZEL, mask=inside, other=0.0).to(tl.float32)
            code = tl.load(SEM + at, mask=inside, other=0).to(tl.int32)
            sem = tl.load(TABLE + code, mask=inside, other=0.0)
            fresh = tl.load(RESETS + n)  # resets[l, m]: element l·M + m = n
            delta = tl.where(fresh != 0, 0.0, now - prev)
        else:
            at = n * s_n + az * s_a + el * s_e  # (BLOCK_A, BLOCK_E) int64
            now = tl.load(OBS + at, mask=inside, other=0.0).to(tl.float32)
            sem = tl.load(OBS + at + s_c, mask=inside, other=0.0).to(tl.float32)
            delta = tl.load(OBS + at + 2 * s_c, mask=inside, other=0.0).to(tl.float32)
        if CAP:  # cap_view's operations: a comparison keeps NaN where clamp(max=) keeps it
            before = now - delta
            before = tl.where(before > view_range, view_range, before)
            sem = tl.where((now > view_range) & (sem >= 0.0), 0.5, sem)
            now = tl.where(now > view_range, view_range, now)
            delta = now - before
        unit = tl.where(now < 0.0, 0.0, tl.where(now > 1.0, 1.0, now))  # near_field's clamp(0, 1)
        near = tl.log(unit + eps) * inv_log_eps
        k: tl.constexpr = PA * PE
        out = OUT + (n * tl.num_programs(1) + p) * (4 * k) + ia * PE + je  # (BLOCK_A, BLOCK_E)
        ty = OUT.dtype.element_ty  # float32, or bf16 rounded to nearest even on the GPU, as torch rounds
        tl.store(out, near.to(ty), mask=inside)
        tl.store(out + k, now.to(ty), mask=inside)
        tl.store(out + 2 * k, sem.to(ty), mask=inside)
        tl.store(out + 3 * k, delta.to(ty), mask=inside)


def _launch(
    out: torch.Tensor,
    obs: torch.Tensor,
    compact: CompactFrames | None,
    patch: tuple[int, int],
    view_range: float,
) -> torch.Tensor:
    """Runs _patch_tokens_kernel into out (N, P, 4·pa·pe) for float32 frames obs (N, 3, Az, El), or for
    `compact` (obs is then compact.depth16, read for the view's shape only)."""
    pa, pe = patch
    az, el = obs.shape[-2:]
    block_a, block_e = triton.next_power_of_2(pa), triton.next_power_of_2(pe)
    cap = 0.0 < view_range < 1.0
    strides: tuple[int, ...] = (0, 0, 0, 0)  # obs's, for float32 frames
    if compact is not None:
        resets = compact.resets.contiguous().view(torch.uint8)  # (L, M)
        chunks, actors = compact.chunks.contiguous(), compact.actors.contiguous()  # (M,) each
        depth16, semantic, table = compact.depth16, compact.semantic, compact.table
        m, na = resets.shape[1], depth16.shape[1]
    else:
        resets = chunks = actors = depth16 = semantic = table = obs  # unused pointers
        m, na, strides = 1, 1, obs.stride()
    grid = (out.shape[0], out.shape[1])
    _patch_tokens_kernel[grid](
        out, obs, *strides, depth16, semantic, resets, table, chunks, actors, m,
        compact.chunk if compact is not None else 1, na, az * el, view_range if cap else 1.0,
        NEAR_FIELD_EPS, 1.0 / math.log(NEAR_FIELD_EPS), EL=el, EL_PATCHES=el // pe, PA=pa, PE=pe,
        BLOCK_A=block_a, BLOCK_E=block_e, COMPACT=compact is not None, CAP=cap,
        num_warps=max(1, min(8, block_a * block_e // 128)),
    )  # fmt: skip
    return out


def patch_tokens_triton(
    obs: torch.Tensor, patch: tuple[int, int], view_range: float, dtype: torch.dtype
) -> torch.Tensor:
    """patch_tokens_ref(obs, patch, view_range).to(dtype) by the kernel: obs (N, 3, Az, El) -> (N, P, 4·pa·pe)."""
    n, _, az, el = obs.shape
    out = torch.empty(n, *_token_shape(az, el, *patch), device=obs.device, dtype=dtype)  # (N, P, 4·pa·pe)
    return _launch(out, obs, None, patch, view_range)


def compact_patch_tokens_triton(
    frames: CompactFrames, patch: tuple[int, int], view_range: float, dtype: torch.dtype
) -> torch.Tensor:
    """The tokens (L·M, P, 4·pa·pe) of a compact minibatch by the kernel: patch_tokens_ref of
    gather_frames(*frames) flattened over (L, M), in `dtype`."""
    az, el = frames.depth16.shape[-2:]
    n = frames.resets.shape[0] * frames.resets.shape[1]
    out = torch.empty(n, *_token_shape(az, el, *patch), device=frames.depth16.device, dtype=dtype)
    return _launch(out, frames.depth16, frames, patch, view_range)


@torch.library.custom_op("navi::patch_tokens", mutates_args=())
def _patch_tokens_op(
    obs: torch.Tensor, pa: int, pe: int, view_range: float, dtype: torch.dtype
) -> torch.Tensor:
    """patch_tokens of float32 frames (N, 3, Az, El) -> (N, P, 4·pa·pe) in dtype: the written-out twin
    here; the kernel on CUDA. An operator of its own, so torch.compile calls it as it is."""
    return patch_tokens_ref(obs, (pa, pe), view_range).to(dtype)


@_patch_tokens_op.register_kernel("cuda")
def _patch_tokens_cuda(
    obs: torch.Tensor, pa: int, pe: int, view_range: float, dtype: torch.dtype
) -> torch.Tensor:
    return patch_tokens_triton(obs, (pa, pe), view_range, dtype)


@_patch_tokens_op.register_fake
def _patch_tokens_fake(
    obs: torch.Tensor, pa: int, pe: int, view_range: float, dtype: torch.dtype
) -> torch.Tensor:
    return obs.new_empty(obs.shape[0], *_token_shape(obs.shape[2], obs.shape[3], pa, pe), dtype=dtype)


@torch.library.custom_op("navi::compact_patch_tokens", mutates_args=())
def _compact_patch_tokens_op(
    depth16: torch.Tensor,
    semantic: torch.Tensor,
    resets: torch.Tensor,
    table: torch.Tensor,
    chunks: torch.Tensor,
    actors: torch.Tensor,
    chunk: int,
    pa: int,
    pe: int,
    view_range: float,
    dtype: torch.dtype,
) -> torch.Tensor:
    """patch_tokens of compact frames -> (L·M, P, 4·pa·pe) in dtype: the written-out twin (gather_frames,
    then patch_tokens_ref) here; the kernel on CUDA."""
    obs = gather_frames(depth16, semantic, resets, table, chunks, actors, chunk)  # (L, M, 3, Az, El)
    return patch_tokens_ref(obs.flatten(0, 1), (pa, pe), view_range).to(dtype)


@_compact_patch_tokens_op.register_kernel("cuda")
def _compact_patch_tokens_cuda(
    depth16: torch.Tensor,
    semantic: torch.Tensor,
    resets: torch.Tensor,
    table: torch.Tensor,
    chunks: torch.Tensor,
    actors: torch.Tensor,
    chunk: int,
    pa: int,
    pe: int,
    view_range: float,
    dtype: torch.dtype,
) -> torch.Tensor:
    frames = CompactFrames(depth16, semantic, resets, table, chunks, actors, chunk)
    return compact_patch_tokens_triton(frames, (pa, pe), view_range, dtype)


@_compact_patch_tokens_op.register_fake
def _compact_patch_tokens_fake(
    depth16: torch.Tensor,
    semantic: torch.Tensor,
    resets: torch.Tensor,
    table: torch.Tensor,
    chunks: torch.Tensor,
    actors: torch.Tensor,
    chunk: int,
    pa: int,
    pe: int,
    view_range: float,
    dtype: torch.dtype,
) -> torch.Tensor:
    n = resets.shape[0] * resets.shape[1]
    return depth16.new_empty(n, *_token_shape(depth16.shape[2], depth16.shape[3], pa, pe), dtype=dtype)


def patch_tokens(
    obs: torch.Tensor | CompactFrames, patch: tuple[int, int], view_range: float, dtype: torch.dtype
) -> torch.Tensor:
    """The encoder's patch tokens in `dtype`: float32 frames obs (N, 3, Az, El) -> (N, P, 4·pa·pe), or a
    compact minibatch (its L steps of M sequences) -> (L·M, P, 4·pa·pe), step-major as
    gather_frames(...).flatten(0, 1). Triton on CUDA, patch_tokens_ref elsewhere; under torch.export (the
    ONNX export) the written-out stage itself, which exports as standard operators."""
    if torch.compiler.is_exporting():
        frames = (
            gather_frames(*obs).flatten(0, 1) if isinstance(obs, CompactFrames) else obs
        )  # (N, 3, Az, El)
        return patch_tokens_ref(frames, patch, view_range).to(dtype)
    pa, pe = patch
    if isinstance(obs, CompactFrames):
        return _compact_patch_tokens_op(*obs[:6], obs.chunk, pa, pe, view_range, dtype)
    return _patch_tokens_op(obs, pa, pe, view_range, dtype)


def frames_device(obs: torch.Tensor | CompactFrames) -> torch.device:
    """The device of float32 frames or of a compact minibatch."""
    return obs.depth16.device if isinstance(obs, CompactFrames) else obs.device
