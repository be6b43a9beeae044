"""The fused short-sequence attention (engine/attention.py): its Triton kernels against the written-out
reference (run on the CPU by Triton's interpreter), the operator's gradient, and the shapes it refuses.
The encoder wired to it is in test_learner_encoder.py, the CUDA run of the kernels in test_learner_gpu.py."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
import torch.nn.functional as F

from navi_learner.config import EngineConfig
from navi_learner.engine.attention import (
    FUSED_HEAD_WIDTHS,
    fused_attention_fits,
    kernel_serves,
    short_attention,
    short_attention_backward_ref,
    short_attention_ref,
    token_block,
)
from navi_learner.engine.encoder import RayViTEncoder

LEARNER = Path(__file__).resolve().parents[2] / "services" / "learner"

INTERPRETED = textwrap.dedent(
    """
    import json, torch
    from navi_learner.engine.attention import (short_attention_backward_ref, short_attention_backward_triton,
        short_attention_ref, short_attention_triton)
    g = torch.Generator().manual_seed(0)
    errors = {}
    for n, p, h, d in [(3, 48, 4, 32), (2, 5, 1, 16), (1, 128, 2, 64)]:
        qkv = torch.randn(n, p, 3, h, d, generator=g)  # (N, P, 3, h, d)
        dout = torch.randn(n, p, h, d, generator=g)  # (N, P, h, d)
        ref, grad = short_attention_ref(qkv), short_attention_backward_ref(qkv, dout)
        for dtype in (torch.float32, torch.float16):
            out = short_attention_triton(qkv.to(dtype)).float()
            dqkv = short_attention_backward_triton(qkv.to(dtype), dout.to(dtype)).float()
            errors[f"{n},{p},{h},{d},{dtype}"] = [
                (out - ref).abs().max().item(), (dqkv - grad).abs().max().item(),
                grad.abs().max().item(), list(out.shape), list(dqkv.shape)]
    print(json.dumps(errors))
    """
)


def test_kernels_match_the_written_out_attention_under_the_interpreter() -> None:
    """Forward and backward kernels against short_attention_ref and its autograd gradient, with the
    sequence padded to the program's block (5 of 16, 48 of 64) and full (128): float32 to rounding,
    float16 to its precision."""
    pytest.importorskip("triton", reason="the kernels are Triton programs; this torch build has no Triton")
    env = {
        **os.environ,
        "TRITON_INTERPRET": "1",
        "PYTHONPATH": f"{LEARNER}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
    }
    run = subprocess.run(
        [sys.executable, "-c", INTERPRETED], env=env, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-2000:]
    import json

    errors = json.loads(run.stdout.strip().splitlines()[-1])
    assert len(errors) == 6
    for key, (out_err, grad_err, grad_max, out_shape, grad_shape) in errors.items():
        n, p, h, d = (int(x) for x in key.split(",")[:4])
        assert out_shape == [n, p, h, d] and grad_shape == [n, p, 3, h, d]
        tol = 1e-5 if "float32" in key else 5e-3
        assert out_err < tol, key
        assert grad_err < tol * max(1.0, grad_max), key


def test_the_operator_is_sdpa_in_value_and_gradient() -> None:
    """short_attention (here its CPU twin, through the registered operator and its autograd) reads
    q, k, v from the qkv layout and returns what F.scaled_dot_product_attention returns, transposed."""
    g = torch.Generator().manual_seed(1)
    qkv = torch.randn(4, 48, 3, 4, 32, generator=g, requires_grad=True)  # (N, P, 3, h, d)
    out = short_attention(qkv)  # (N, P, h, d)
    q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)  # (N, h, P, d) each
    ref = F.scaled_dot_product_attention(q, k, v).transpose(1, 2)  # (N, P, h, d)
    assert out.shape == (4, 48, 4, 32)
    assert torch.allclose(out, ref, atol=1e-5, rtol=0)
    dout = torch.randn(out.shape, generator=g)  # (N, P, h, d)
    (got,) = torch.autograd.grad(out, qkv, dout)
    (want,) = torch.autograd.grad(ref, qkv, dout)
    assert torch.allclose(got, want, atol=1e-5, rtol=0)
    assert torch.equal(short_attention_backward_ref(qkv, dout), got)
    assert torch.equal(short_attention_ref(qkv.detach()), out.detach())


def test_shapes_the_kernel_cannot_hold_are_refused_with_the_reason() -> None:
    assert fused_attention_fits(48, 32) is None and fused_attention_fits(128, 16) is None
    assert "129 tokens" in str(fused_attention_fits(129, 32))
    assert "heads 24 wide" in str(fused_attention_fits(48, 24))
    with pytest.raises(ValueError, match="attention fused cannot take this encoder: heads 8 wide"):
        RayViTEncoder((3, 32, 8), EngineConfig.tiny(attention="fused", encoder_heads=4))  # 32 / 4 = 8
    with pytest.raises(ValueError, match="192 tokens"):
        RayViTEncoder((3, 256, 48), EngineConfig(attention="fused", patch_size=8, patch_el=8))


SM90_SHARED_BYTES = 232_448
"""The most shared memory one block may take on sm_90 (227 KiB): a kernel compiled for more fails to launch."""
TRITON_TYPE = {torch.float32: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}


def test_the_kernels_serve_every_shape_in_half_precision_and_small_ones_in_float32() -> None:
    """kernel_serves: bf16 and float16 over the whole envelope, float32 up to a 64-row block of heads
    32 wide (or 16 rows of 128), nothing else (float64 runs the written-out twin)."""
    for tokens in (5, 48, 128):
        for width in FUSED_HEAD_WIDTHS:
            assert kernel_serves(tokens, width, torch.bfloat16) and kernel_serves(
                tokens, width, torch.float16
            )
    assert token_block(5) == 16 and token_block(48) == 64 and token_block(64) == 64 and token_block(65) == 128
    assert kernel_serves(48, 32, torch.float32) and kernel_serves(16, 128, torch.float32)
    assert not kernel_serves(48, 64, torch.float32) and not kernel_serves(65, 16, torch.float32)
    assert not kernel_serves(48, 32, torch.float64)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32], ids=TRITON_TYPE.get)
def test_kernels_compile_for_hopper_wherever_they_serve(
    hopper_compile: Callable[..., dict[str, Any]], dtype: torch.dtype
) -> None:
    """The forward and backward kernels, as the host code launches them, compile for sm_90 to a cubin on
    this CPU machine (the interpreter above runs them without compiling them), at every block and head
    width they serve in `dtype`, and fit in a block's shared memory."""
    from navi_learner.engine.attention import _short_attention_bwd, _short_attention_fwd

    t = TRITON_TYPE[dtype]
    served = 0
    for block in (16, 32, 64, 128):
        for width in FUSED_HEAD_WIDTHS:
            if not kernel_serves(block, width, dtype):
                continue
            served += 1
            shape = {"H": 4, "D": width, "BLOCK": block, "IEEE": dtype == torch.float32}
            const = {name: "constexpr" for name in shape}
            fwd = hopper_compile(
                _short_attention_fwd,
                {"QKV": f"*{t}", "OUT": f"*{t}", "P": "i32", "scale": "fp32", **const},
                shape,
            )
            bwd = hopper_compile(
                _short_attention_bwd,
                {"QKV": f"*{t}", "DOUT": f"*{t}", "DQKV": f"*{t}", "P": "i32", "scale": "fp32", **const},
                shape,
            )
            for kernel in (fwd, bwd):
                assert len(kernel["cubin"]) > 0 and ".target sm_90" in kernel["ptx"], (block, width)
                assert kernel["shared"] <= SM90_SHARED_BYTES, (block, width, kernel["shared"])
    assert served == (16 if dtype != torch.float32 else 9)
