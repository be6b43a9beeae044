"""copy_rows against its torch twin: the selected rows copied, the others untouched, on the CPU (the
twin itself) and on CUDA (the Triton kernel, rows that are not a multiple of its chunk)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import torch

from navi_env.ecosystem.rows import CHUNK, _kernel, copy_rows, copy_rows_ref


def case(device: str, n: int, shape: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator(device=device).manual_seed(n)
    dst = torch.rand(n, *shape, generator=g, device=device)  # (N, ...)
    src = torch.rand(n, *shape, generator=g, device=device)  # (N, ...)
    mask = torch.rand(n, generator=g, device=device) < 0.3  # (N,) bool
    mask[0], mask[-1] = True, False
    return dst, src, mask


def test_copy_rows_ref_copies_the_selected_rows_only() -> None:
    dst, src, mask = case("cpu", 17, (3, 5, 4))
    want = dst.clone()
    want[mask] = src[mask]
    copy_rows(dst, src, mask)
    assert torch.equal(dst, want)
    with pytest.raises(ValueError, match="under a mask"):
        copy_rows(dst, src, mask[:-1])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("shape", [(3, 256, 48), (3, 7, 5), (4,)])
def test_copy_rows_kernel_matches_the_reference_on_cuda(shape: tuple[int, ...]) -> None:
    dst, src, mask = case("cuda", 257, shape)
    ref = dst.clone()
    copy_rows_ref(ref, src, mask)
    copy_rows(dst, src, mask)
    assert torch.equal(dst, ref)
    none = torch.zeros_like(mask)
    before = dst.clone()
    copy_rows(dst, src, none)
    assert torch.equal(dst, before)


@pytest.mark.parametrize("dtype", ["fp32", "bf16", "u8"])
def test_copy_rows_kernel_compiles_for_hopper(
    hopper_compile: Callable[..., dict[str, Any]], dtype: str
) -> None:
    """The kernel, as copy_rows launches it (any element type, a uint8 mask, the row length), compiles
    for sm_90 to a cubin on this CPU machine."""
    kernel = _kernel()
    assert kernel is not None  # hopper_compile has skipped where Triton is missing
    signature = {"dst": f"*{dtype}", "src": f"*{dtype}", "mask": "*u8", "row": "i32", "chunk": "constexpr"}
    asm = hopper_compile(kernel, signature, {"chunk": CHUNK})
    assert len(asm["cubin"]) > 0
    assert ".target sm_90" in asm["ptx"]
