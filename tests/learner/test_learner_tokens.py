"""The encoder's input stage (engine/tokens.py): the written-out twin against the stage spelled out
channel by channel, its operators on the CPU and under torch.compile, the encoder fed compact frames, and
the Triton kernel against the twin under Triton's interpreter and compiled for sm_90. The CUDA run of the
kernel is in test_learner_gpu.py."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch

from navi_env.sim.observation import semantic_table
from navi_learner.config import EngineConfig
from navi_learner.engine.encoder import RayViTEncoder
from navi_learner.engine.tokens import (
    NEAR_FIELD_EPS,
    CompactFrames,
    gather_frames,
    patch_tokens,
    patch_tokens_ref,
)

ROOT = Path(__file__).resolve().parents[2]


def compact_frames(
    t_len: int, actors: int, az: int, el: int, chunk: int, seed: int = 0, goal_marks: bool = True
) -> CompactFrames:
    """Random compact storage of T steps × `actors` and a minibatch of all its sequences in a shuffled
    order (M = T/L · actors): depths in [0, 1] with exact misses (1.0), every semantic code (goal marks
    included), episode starts, and the resets as the storage's (L, M) view (not contiguous)."""
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(t_len + 1, actors, az, el, generator=g)  # (T+1, N, Az, El)
    depth = torch.where(torch.rand(depth.shape, generator=g) < 0.2, 1.0, depth).half()
    semantic = torch.randint(
        0, 256, (t_len, actors, az, el), generator=g, dtype=torch.uint8
    )  # (T, N, Az, El)
    resets = torch.rand(t_len, actors, generator=g) < 0.2  # (T, N) bool
    order = torch.randperm((t_len // chunk) * actors, generator=g)  # (M,)
    chunks, ids = order // actors, order % actors  # (M,) each
    seq = resets.view(t_len // chunk, chunk, actors)[chunks, :, ids].transpose(0, 1)  # (L, M) view
    return CompactFrames(depth, semantic, seq, semantic_table("cpu", goal_marks), chunks, ids, chunk)


def spelled_out(obs: torch.Tensor, patch: tuple[int, int], view_range: float) -> torch.Tensor:
    """The stage for each ray on its own (N, 3, Az, El) -> (N, P, 4·pa·pe): the cap, then near field,
    depth, semantic and delta as the patch's four blocks."""
    depth, semantic, delta = obs.unbind(1)  # (N, Az, El) each
    if 0.0 < view_range < 1.0:
        before = torch.minimum(depth - delta, torch.tensor(view_range))  # (N, Az, El)
        semantic = torch.where((depth > view_range) & (semantic >= 0), 0.5, semantic)
        depth = torch.minimum(depth, torch.tensor(view_range))
        delta = depth - before
    near = torch.log(depth.clamp(0.0, 1.0) + NEAR_FIELD_EPS) * (1.0 / math.log(NEAR_FIELD_EPS))
    pa, pe = patch
    n, az, el = depth.shape
    rows = []
    for a in range(az // pa):
        for e in range(el // pe):
            cut = (slice(None), slice(a * pa, (a + 1) * pa), slice(e * pe, (e + 1) * pe))
            rows.append(torch.cat([c[cut].reshape(n, -1) for c in (near, depth, semantic, delta)], dim=1))
    return torch.stack(rows, dim=1)  # (N, P, 4·pa·pe)


@pytest.mark.parametrize("view_range", [1.0, 0.2])
def test_the_written_out_stage_is_each_ray_capped_and_laid_out_in_its_patch(view_range: float) -> None:
    frames = compact_frames(8, 3, 12, 6, 4)
    obs = gather_frames(*frames).flatten(0, 1)  # (L·M, 3, Az, El) float32
    assert bool((obs[:, 1] < 0).any()) and bool((obs[:, 2] != 0).any())  # goal marks and deltas
    for patch in ((3, 2), (12, 6), (1, 1)):
        assert torch.equal(patch_tokens_ref(obs, patch, view_range), spelled_out(obs, patch, view_range))


def test_the_operators_on_the_cpu_are_the_written_out_stage_in_the_asked_dtype() -> None:
    frames = compact_frames(8, 3, 12, 6, 4)
    obs = gather_frames(*frames).flatten(0, 1)  # (L·M, 3, Az, El)
    for view_range in (1.0, 0.2):
        want = patch_tokens_ref(obs, (3, 2), view_range)  # (L·M, P, 24)
        assert want.shape == (obs.shape[0], 12, 24)
        assert torch.equal(patch_tokens(obs, (3, 2), view_range, torch.float32), want)
        assert torch.equal(patch_tokens(frames, (3, 2), view_range, torch.float32), want)
        assert torch.equal(patch_tokens(frames, (3, 2), view_range, torch.bfloat16), want.bfloat16())


def test_the_encoder_reads_compact_frames_as_the_frames_they_decode_to() -> None:
    """Compact frames (L steps of M sequences) give, row for row, the embeddings of the float32 frames
    gather_frames decodes them to, flattened step-major; eager and traced (aot_eager) alike."""
    torch.manual_seed(0)
    enc = RayViTEncoder((3, 12, 6), EngineConfig.tiny(patch_size=3, patch_el=2, view_range=0.2)).eval()
    frames = compact_frames(8, 3, 12, 6, 4)
    obs = gather_frames(*frames).flatten(0, 1)  # (L·M, 3, Az, El)
    traced = torch.compile(enc, backend="aot_eager", fullgraph=True, dynamic=False)
    with torch.no_grad():
        want = enc(obs)  # (L·M, D)
        assert torch.equal(enc(frames), want)
        assert torch.equal(traced(frames), want)
        assert torch.equal(traced(obs), want)


INTERPRETED = textwrap.dedent(
    """
    import json, sys, torch
    sys.path.insert(0, sys.argv[1])
    from test_learner_tokens import compact_frames
    from navi_learner.engine.tokens import (compact_patch_tokens_triton, gather_frames, patch_tokens_ref,
        patch_tokens_triton)
    errors = {}
    for az, el, patch in [(32, 16, (16, 16)), (12, 6, (3, 2))]:
        frames = compact_frames(8, 3, az, el, 4)
        obs = gather_frames(*frames).flatten(0, 1)  # (L·M, 3, Az, El)
        for view_range in (1.0, 0.2):
            ref = patch_tokens_ref(obs, patch, view_range)
            for dtype in (torch.float32, torch.bfloat16):
                want = ref.to(dtype).float()
                a = patch_tokens_triton(obs, patch, view_range, dtype).float()
                b = compact_patch_tokens_triton(frames, patch, view_range, dtype).float()
                c = patch_tokens_triton(obs.transpose(2, 3).contiguous().transpose(2, 3), patch, view_range, dtype)
                ulp = want.abs() * (2**-7 if dtype == torch.bfloat16 else 2**-23) + 2**-24  # (N, P, K)
                errors[f"{az},{el},{patch},{view_range},{dtype}"] = [
                    ((a - want).abs() / ulp).max().item(), ((b - want).abs() / ulp).max().item(),
                    torch.equal(a, b), torch.equal(c.float(), a), list(a.shape), list(want.shape)]
    print(json.dumps(errors))
    """
)


def test_the_kernel_is_the_written_out_stage_under_the_interpreter() -> None:
    """Float32 frames and compact ones (a shuffled minibatch, resets not contiguous), frames with other
    strides, patches of powers of two and not (3 × 2, padded to 4 × 2), with and without the view cap:
    the kernel's tokens are the twin's within a unit in the last place, or 2^-24 near zero (the
    interpreter's log is numpy's, the twin's torch's; its bf16 casts truncate where the GPU's round to
    nearest), and both entries agree bit for bit."""
    pytest.importorskip("triton", reason="the kernel is a Triton program; this torch build has no Triton")
    path = [
        str(ROOT / "services" / "learner"),
        str(ROOT / "services" / "env"),
        os.environ.get("PYTHONPATH", ""),
    ]
    env = {**os.environ, "TRITON_INTERPRET": "1", "PYTHONPATH": os.pathsep.join(path)}
    run = subprocess.run(
        [sys.executable, "-c", INTERPRETED, str(Path(__file__).parent)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    errors = json.loads(run.stdout.strip().splitlines()[-1])
    assert len(errors) == 8
    for key, (ulps_a, ulps_b, same, strided, shape, want_shape) in errors.items():
        assert shape == want_shape, key
        assert ulps_a <= 1.0 and ulps_b <= 1.0, key
        assert same and strided, key


TRITON_TYPE = {torch.float32: "fp32", torch.bfloat16: "bf16"}


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float32], ids=TRITON_TYPE.get)
@pytest.mark.parametrize("compact", [False, True], ids=["frames", "compact"])
def test_the_kernel_compiles_for_hopper(
    hopper_compile: Callable[..., dict[str, Any]], compact: bool, dtype: torch.dtype
) -> None:
    """The kernel, as _launch launches it at the canonical 256 × 48 view in 16 × 16 and 32 × 16 patches,
    capped and not, compiles for sm_90 to a cubin on this CPU machine, without shared memory."""
    from navi_learner.engine.tokens import _patch_tokens_kernel

    signature = {
        "OUT": f"*{TRITON_TYPE[dtype]}",
        "OBS": "*fp16" if compact else "*fp32",
        **{s: "i64" for s in ("s_n", "s_c", "s_a", "s_e")},
        "DEPTH": "*fp16",
        "SEM": "*u8",
        "RESETS": "*u8",
        "TABLE": "*fp32",
        "CHUNKS": "*i64",
        "ACTORS": "*i64",
        **{s: "i32" for s in ("M", "L", "NA", "AZEL")},
        **{s: "fp32" for s in ("view_range", "eps", "inv_log_eps")},
    }
    for pa in (16, 32):
        for cap in (False, True):
            constexprs = {"EL": 48, "EL_PATCHES": 3, "PA": pa, "PE": 16, "BLOCK_A": pa, "BLOCK_E": 16}
            constexprs |= {"COMPACT": compact, "CAP": cap}
            signature |= {k: "constexpr" for k in constexprs}
            asm = hopper_compile(_patch_tokens_kernel, signature, constexprs)
            assert asm["cubin"] and asm["shared"] == 0
