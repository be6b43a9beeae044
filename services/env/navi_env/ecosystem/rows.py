"""Copy the rows of a batch that a mask selects, without reading the others and without asking the host:
what an adapter needs to write the final views of the few actors whose episode ended into a new
observation tensor (N, 3, Az, El), where a masked `torch.where` would read both tensors whole and a
boolean index would wait for the device to count the rows.

`copy_rows` is one Triton kernel on CUDA (each program looks at its row's flag and copies one chunk of
the row only when it is set); `copy_rows_ref` is the obviously correct torch twin, used on the CPU and
wherever Triton is missing.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch

CHUNK = 4096
"""Elements one program copies (a row of N x 3 x 256 x 48 is 36,864: nine programs)."""


def copy_rows_ref(dst: torch.Tensor, src: torch.Tensor, mask: torch.Tensor) -> None:
    """dst[i] = src[i] for every row i where mask (N,) bool is set; dst and src (N, ...) alike."""
    dst.copy_(torch.where(mask.view(-1, *([1] * (dst.ndim - 1))), src, dst))


def copy_rows(dst: torch.Tensor, src: torch.Tensor, mask: torch.Tensor) -> None:
    """copy_rows_ref without reading the unselected rows or synchronising (CUDA, contiguous float32
    tensors); falls back to copy_rows_ref elsewhere."""
    if dst.shape != src.shape or mask.shape != dst.shape[:1]:
        raise ValueError(
            f"rows of {tuple(dst.shape)} from {tuple(src.shape)} under a mask {tuple(mask.shape)}"
        )
    kernel = _kernel() if dst.is_cuda else None
    if kernel is None or not (dst.is_contiguous() and src.is_contiguous()) or dst.dtype != src.dtype:
        copy_rows_ref(dst, src, mask)
        return
    n = dst.shape[0]
    row = dst.numel() // max(n, 1)
    if n and row:
        kernel[(n, (row + CHUNK - 1) // CHUNK)](dst, src, mask.view(torch.uint8), row, CHUNK)


@functools.cache
def _kernel() -> Any | None:
    """The Triton kernel, compiled on first launch; None where Triton is not installed."""
    try:
        import triton
        import triton.language as tl
    except ImportError:
        return None

    @triton.jit
    def copy_selected_rows(dst, src, mask, row, chunk: tl.constexpr):  # type: ignore[no-untyped-def]
        i = tl.program_id(0).to(tl.int64)  # the row
        if tl.load(mask + i) != 0:
            at = tl.program_id(1) * chunk + tl.arange(0, chunk)  # (chunk,) elements of this program
            inside = at < row
            value = tl.load(src + i * row + at, mask=inside)
            tl.store(dst + i * row + at, value, mask=inside)

    launcher: Callable[..., Any] = copy_selected_rows
    return launcher
