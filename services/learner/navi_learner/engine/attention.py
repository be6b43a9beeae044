"""The encoder's multi-head attention over a view's few tokens (48 at 256×48 with 16 × 16 patches).

Three ways to compute the same function softmax(q kᵀ / √d) v, picked by `EngineConfig.attention` (its
default, auto, is fused on CUDA where `fused_attention_fits`, sdpa otherwise):
- sdpa: F.scaled_dot_product_attention, which picks a fused library kernel;
- explicit: the products and the softmax written out (`attention_explicit`), for torch.compile to fuse;
- fused: `short_attention`, one Triton program per (sample, head) holding the whole sequence, all its
  scores and its softmax in registers. It reads q, k and v straight from the qkv projection's output
  (N, P, 3, h, d) and writes (N, P, h, d), the layout the output projection reads, so no permuted copy
  is made either way; its backward recomputes the scores and writes the qkv gradient in place of the
  three. Library flash kernels tile for long sequences: the cuDNN forward profiled at 48 tokens runs
  64 × 128 tiles, and with its backward takes 31% of an update. CUDA runs the kernels (float32 only
  up to FLOAT32_KERNEL_TILE); the CPU runs `short_attention_ref`, the slow and obviously correct twin
  the kernels are tested against (the kernels also run on the CPU under TRITON_INTERPRET=1, and are
  compiled for sm_90 on the CPU, for those tests). Measured on an H200 at 8,192 actors, the fused
  attention trains 13–15% more steps per second than SDPA, and learned no worse with seeds interleaved
(docs/PERFORMANCE.md).

Legend: N samples, P tokens, h heads, d = D/h head width.
"""

from __future__ import annotations

import math
from typing import Any

import torch

try:  # the kernels need Triton (it comes with torch's CUDA builds); without it the CPU twin serves
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - every torch build with CUDA ships Triton
    triton = None

FUSED_MAX_TOKENS = 128
"""The most tokens `short_attention` takes: a (sample, head)'s scores stay in one program's registers."""
FUSED_HEAD_WIDTHS = (16, 32, 64, 128)
"""Head widths `short_attention` takes (a power of two, at least the 16 a tensor-core product needs)."""
FLOAT32_KERNEL_TILE = 2048
"""The largest block × head width the kernels serve in float32 (at most 64 tokens' block). Full-precision
products run on the CUDA cores, not the tensor cores, and larger tiles take minutes to compile (128
tokens of heads 32 wide: about 130 s for the backward) or more shared memory than a block holds (128 ×
64); there float32 attention on CUDA runs the written-out twin instead. bf16 and float16 take every
shape `fused_attention_fits` allows."""


def attention_explicit(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """softmax(q kᵀ / √d) v written out, the softmax in float32: q, k, v (N, h, P, d) -> (N, h, P, d).
    The same function as F.scaled_dot_product_attention(q, k, v)."""
    w = torch.matmul(q, k.transpose(-2, -1)).float() * (1.0 / math.sqrt(q.shape[-1]))  # (N, h, P, P) f32
    return torch.matmul(w.softmax(dim=-1).to(v.dtype), v)  # (N, h, P, d)


def short_attention_ref(qkv: torch.Tensor) -> torch.Tensor:
    """Attention of the qkv projection's output (N, P, 3, h, d) -> (N, P, h, d), written out
    (attention_explicit): what the kernels compute."""
    q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)  # (N, h, P, d) each
    return attention_explicit(q, k, v).transpose(1, 2).contiguous()  # (N, P, h, d)


def token_block(tokens: int) -> int:
    """The kernels' block of rows for `tokens` tokens: the next power of two, at least 16."""
    return max(16, 1 << (tokens - 1).bit_length())


def kernel_serves(tokens: int, head_width: int, dtype: torch.dtype) -> bool:
    """Whether the Triton kernels compute a shape `fused_attention_fits` allows in `dtype` on CUDA (else
    the written-out twin does): bf16 and float16 always, float32 up to FLOAT32_KERNEL_TILE."""
    if dtype in (torch.bfloat16, torch.float16):
        return True
    block = token_block(tokens)
    return dtype == torch.float32 and block <= 64 and block * head_width <= FLOAT32_KERNEL_TILE


def fused_attention_fits(tokens: int, head_width: int) -> str | None:
    """Why `short_attention` cannot serve `tokens` tokens of heads `head_width` wide, or None if it can."""
    if tokens > FUSED_MAX_TOKENS:
        return f"{tokens} tokens, more than the {FUSED_MAX_TOKENS} it holds in one program"
    if head_width not in FUSED_HEAD_WIDTHS:
        widths = ", ".join(map(str, FUSED_HEAD_WIDTHS))
        return f"heads {head_width} wide; it takes {widths}"
    return None


if triton is not None:

    @triton.jit
    def _dot(a, b, IEEE: tl.constexpr):  # type: ignore[no-untyped-def]
        """a @ b accumulated in float32; float32 operands multiplied in full precision, not TF32."""
        if IEEE:
            return tl.dot(a, b, input_precision="ieee")
        return tl.dot(a, b)

    @triton.jit
    def _qkv_and_probs(  # type: ignore[no-untyped-def]
        QKV, P, scale, H: tl.constexpr, D: tl.constexpr, BLOCK: tl.constexpr, IEEE: tl.constexpr,
    ):  # fmt: skip
        """This program's (sample, head): q, k, v (BLOCK, D), their softmax probabilities (BLOCK, BLOCK)
        float32 (padded rows and columns read as zero), the row offsets, the column offsets, the valid
        rows, and the sample."""
        pid = tl.program_id(0)
        n = (pid // H).to(tl.int64)
        head = pid % H
        rows = tl.arange(0, BLOCK)
        cols = tl.arange(0, D)
        valid = rows < P
        at = QKV + n * P * (3 * H * D) + head * D + rows[:, None] * (3 * H * D) + cols[None, :]
        q = tl.load(at, mask=valid[:, None], other=0.0)  # (BLOCK, D)
        k = tl.load(at + H * D, mask=valid[:, None], other=0.0)  # (BLOCK, D)
        v = tl.load(at + 2 * H * D, mask=valid[:, None], other=0.0)  # (BLOCK, D)
        s = _dot(q, tl.trans(k), IEEE) * scale  # (BLOCK, BLOCK) float32
        s = tl.where(valid[None, :], s, float("-inf"))
        e = tl.exp(s - tl.max(s, axis=1)[:, None])
        probs = e / tl.sum(e, axis=1)[:, None]  # (BLOCK, BLOCK) float32
        return q, k, v, probs, rows, cols, valid, n, head

    @triton.jit
    def _short_attention_fwd(  # type: ignore[no-untyped-def]
        QKV, OUT, P, scale, H: tl.constexpr, D: tl.constexpr, BLOCK: tl.constexpr, IEEE: tl.constexpr,
    ):  # fmt: skip
        _q, _k, v, probs, rows, cols, valid, n, head = _qkv_and_probs(QKV, P, scale, H, D, BLOCK, IEEE)
        o = _dot(probs.to(v.dtype), v, IEEE)  # (BLOCK, D) float32
        at = OUT + n * P * (H * D) + head * D + rows[:, None] * (H * D) + cols[None, :]
        tl.store(at, o.to(OUT.dtype.element_ty), mask=valid[:, None])

    @triton.jit
    def _short_attention_bwd(  # type: ignore[no-untyped-def]
        QKV, DOUT, DQKV, P, scale, H: tl.constexpr, D: tl.constexpr, BLOCK: tl.constexpr,
        IEEE: tl.constexpr,
    ):  # fmt: skip
        q, k, v, probs, rows, cols, valid, n, head = _qkv_and_probs(QKV, P, scale, H, D, BLOCK, IEEE)
        at_out = DOUT + n * P * (H * D) + head * D + rows[:, None] * (H * D) + cols[None, :]
        do = tl.load(at_out, mask=valid[:, None], other=0.0)  # (BLOCK, D)
        o = _dot(probs.to(v.dtype), v, IEEE)  # (BLOCK, D) float32, the forward's output
        delta = tl.sum(do.to(tl.float32) * o, axis=1)  # (BLOCK,) float32
        dv = _dot(tl.trans(probs.to(do.dtype)), do, IEEE)  # (BLOCK, D) float32
        dp = _dot(do, tl.trans(v), IEEE)  # (BLOCK, BLOCK) float32
        ds = probs * (dp - delta[:, None])  # (BLOCK, BLOCK) float32, zero on padding
        dq = _dot(ds.to(k.dtype), k, IEEE) * scale  # (BLOCK, D) float32
        dk = _dot(tl.trans(ds.to(q.dtype)), q, IEEE) * scale  # (BLOCK, D) float32
        at = DQKV + n * P * (3 * H * D) + head * D + rows[:, None] * (3 * H * D) + cols[None, :]
        kind = DQKV.dtype.element_ty
        tl.store(at, dq.to(kind), mask=valid[:, None])
        tl.store(at + H * D, dk.to(kind), mask=valid[:, None])
        tl.store(at + 2 * H * D, dv.to(kind), mask=valid[:, None])


def _launch_shape(qkv: torch.Tensor) -> tuple[int, int, int, int, int]:
    """(N, P, h, d, BLOCK) of a qkv (N, P, 3, h, d) the kernels take; ValueError otherwise."""
    if triton is None:
        raise RuntimeError("short_attention's kernels need Triton (pip install triton)")
    if qkv.dim() != 5 or qkv.shape[2] != 3:
        raise ValueError(f"qkv must be (N, P, 3, h, d), got {tuple(qkv.shape)}")
    n, p, _, h, d = qkv.shape
    why = fused_attention_fits(p, d)
    if why is not None:
        raise ValueError(f"short_attention cannot take {why}")
    return n, p, h, d, token_block(p)


def short_attention_triton(qkv: torch.Tensor) -> torch.Tensor:
    """The forward kernel: qkv (N, P, 3, h, d) -> (N, P, h, d), one program per (sample, head)."""
    n, p, h, d, block = _launch_shape(qkv)
    qkv = qkv.contiguous()
    out = torch.empty(n, p, h, d, dtype=qkv.dtype, device=qkv.device)  # (N, P, h, d)
    ieee = qkv.dtype == torch.float32
    _short_attention_fwd[(n * h,)](qkv, out, p, 1.0 / math.sqrt(d), H=h, D=d, BLOCK=block, IEEE=ieee)
    return out


def short_attention_backward_triton(qkv: torch.Tensor, dout: torch.Tensor) -> torch.Tensor:
    """The backward kernel: the gradient (N, P, 3, h, d) of qkv for the output's gradient (N, P, h, d)."""
    n, p, h, d, block = _launch_shape(qkv)
    qkv, dout = qkv.contiguous(), dout.contiguous().to(qkv.dtype)
    dqkv = torch.empty_like(qkv)  # (N, P, 3, h, d)
    ieee = qkv.dtype == torch.float32
    _short_attention_bwd[(n * h,)](qkv, dout, dqkv, p, 1.0 / math.sqrt(d), H=h, D=d, BLOCK=block, IEEE=ieee)
    return dqkv


def short_attention_backward_ref(qkv: torch.Tensor, dout: torch.Tensor) -> torch.Tensor:
    """The gradient (N, P, 3, h, d) of short_attention_ref for the output's gradient dout (N, P, h, d),
    written out in float32 (the softmax's backward: dS = P ∘ (dP − rowsum(dP ∘ P)))."""
    q, k, v = qkv.float().permute(2, 0, 3, 1, 4).unbind(0)  # (N, h, P, d) each
    do = dout.float().transpose(1, 2)  # (N, h, P, d)
    scale = 1.0 / math.sqrt(q.shape[-1])
    probs = (torch.matmul(q, k.transpose(-2, -1)) * scale).softmax(dim=-1)  # (N, h, P, P)
    dv = torch.matmul(probs.transpose(-2, -1), do)  # (N, h, P, d)
    dp = torch.matmul(do, v.transpose(-2, -1))  # (N, h, P, P)
    ds = probs * (dp - (dp * probs).sum(dim=-1, keepdim=True))  # (N, h, P, P)
    dq = torch.matmul(ds, k) * scale  # (N, h, P, d)
    dk = torch.matmul(ds.transpose(-2, -1), q) * scale  # (N, h, P, d)
    grad = torch.stack([dq, dk, dv]).permute(1, 3, 0, 2, 4)  # (N, P, 3, h, d)
    return grad.to(qkv.dtype).contiguous()


@torch.library.custom_op("navi::short_attention", mutates_args=())
def short_attention(qkv: torch.Tensor) -> torch.Tensor:
    """Attention of the qkv projection's output (N, P, 3, h, d) -> (N, P, h, d): the Triton kernel on
    CUDA where `kernel_serves`, short_attention_ref elsewhere. An operator of its own, so torch.compile
    calls it as it is."""
    return short_attention_ref(qkv)


@short_attention.register_kernel("cuda")
def _short_attention_cuda(qkv: torch.Tensor) -> torch.Tensor:
    if kernel_serves(qkv.shape[1], qkv.shape[-1], qkv.dtype):
        return short_attention_triton(qkv)
    return short_attention_ref(qkv)


@short_attention.register_fake
def _short_attention_fake(qkv: torch.Tensor) -> torch.Tensor:
    n, p, _, h, d = qkv.shape
    return qkv.new_empty(n, p, h, d)


@torch.library.custom_op("navi::short_attention_backward", mutates_args=())
def short_attention_backward(qkv: torch.Tensor, dout: torch.Tensor) -> torch.Tensor:
    """The gradient (N, P, 3, h, d) of qkv through short_attention."""
    return short_attention_backward_ref(qkv, dout)


@short_attention_backward.register_kernel("cuda")
def _short_attention_backward_cuda(qkv: torch.Tensor, dout: torch.Tensor) -> torch.Tensor:
    if kernel_serves(qkv.shape[1], qkv.shape[-1], qkv.dtype):
        return short_attention_backward_triton(qkv, dout)
    return short_attention_backward_ref(qkv, dout)


@short_attention_backward.register_fake
def _short_attention_backward_fake(qkv: torch.Tensor, dout: torch.Tensor) -> torch.Tensor:
    return torch.empty_like(qkv)


def _setup(ctx: Any, inputs: tuple[torch.Tensor], output: torch.Tensor) -> None:
    ctx.save_for_backward(inputs[0])


def _backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
    (qkv,) = ctx.saved_tensors
    return short_attention_backward(qkv, grad)


short_attention.register_autograd(_backward, setup_context=_setup)
