"""CUDA checks of the learner: core parity on the GPU, the bf16 training path, CPU/GPU agreement."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.engine.attention import (
    kernel_serves,
    short_attention,
    short_attention_backward_ref,
    short_attention_ref,
)
from navi_learner.engine.encoder import RayViTEncoder
from navi_learner.engine.temporal import make_core
from navi_learner.envs.toy import ToyEnv
from navi_learner.ppo.timing import StageTimers
from navi_learner.ppo.train import train

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(
        not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)"
    ),
]


@pytest.mark.parametrize("name", ["mamba2", "gru"])
def test_core_step_loop_equals_sequence_pass_on_cuda(name: str) -> None:
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    torch.manual_seed(0)
    cfg = EngineConfig(embed_dim=64, ssm_head_dim=32, ssm_chunk=16, temporal_core=name)  # type: ignore[arg-type]
    dev = torch.device("cuda")
    core = make_core(cfg).to(dev)
    t_len, n = 40, 256
    x = torch.randn(t_len, n, 64, device=dev)
    resets = torch.rand(t_len, n, device=dev) < 0.1
    state = tuple(torch.randn_like(s) for s in core.initial_state(n, dev))
    with torch.no_grad():
        y_seq, _ = core(x, resets, state)
        ys, s = [], state
        for t in range(t_len):
            y, s = core.step(x[t], resets[t], s)
            ys.append(y)
    assert torch.allclose(y_seq, torch.stack(ys), atol=1e-4, rtol=0)
    cpu_core = make_core(cfg)
    cpu_core.load_state_dict({k: v.cpu() for k, v in core.state_dict().items()})
    with torch.no_grad():
        y_cpu, _ = cpu_core(x.cpu(), resets.cpu(), tuple(v.cpu() for v in state))
    assert torch.allclose(y_seq.cpu(), y_cpu, atol=1e-4, rtol=0)


def test_bf16_training_on_cuda_learns_and_stays_finite(tmp_path: Path) -> None:
    eng = EngineConfig(embed_dim=64, patch_size=8, encoder_layers=2, encoder_heads=4, ssm_chunk=16)
    ppo = PPOConfig(lr=2e-3, num_minibatches=2, bptt_chunk=16, ppo_epochs=2, ent_coef=0.0)
    cfg = TrainConfig(
        n_actors=256,
        rollout_length=32,
        total_steps=256 * 32 * 30,
        device="cuda",
        engine=eng,
        ppo=ppo,
        checkpoint_every=10**9,
        log_every=10,
        compile=False,
    )
    result = train(ToyEnv(256, "cuda", az=64, el=16, seed=1), cfg, run_dir=tmp_path / "run", progress=False)
    assert result.skipped_updates == 0
    assert result.last_metrics["reward_per_step"] > 0.3


def test_exact_stage_timers_measure_gpu_time_without_waiting_for_it() -> None:
    """With sync, a stage's time is the GPU's (events around it, read at the log line): a stage that only
    queues GPU work returns to the host at once but is timed as long as that work runs."""
    cycles = 20_000_000  # torch.cuda._sleep: about 10-20 ms of GPU time

    def gpu_ms() -> float:  # the same work, timed alone
        probe = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        probe[0].record()
        torch.cuda._sleep(cycles)
        probe[1].record()
        probe[1].synchronize()
        return probe[0].elapsed_time(probe[1])

    gpu_ms()  # clocks up
    timers = StageTimers(sync=True)
    for _ in range(2):  # the second read reuses the first read's events
        t0 = time.perf_counter()
        with timers("env"):
            torch.cuda._sleep(cycles)
        with timers("learn"):
            pass
        host_ms = 1000.0 * (time.perf_counter() - t0)
        ms = timers.read(steps=2)  # ms per step: 2 steps
        want = gpu_ms() / 2
        assert host_ms < want
        assert abs(ms["ms_env"] - want) < 0.2 * want, (ms, want)
        assert ms["ms_learn"] < 0.1 * want and ms["ms_forward"] == 0.0
    assert len(timers.pool) == 4 and not timers.spans


def test_compiled_encoder_with_a_view_range_matches_eager_and_ignores_the_far_field_on_cuda() -> None:
    """The encoder as training compiles it, with the point-goal view range (0.2): within float tolerance of
    the eager encoder, and blind beyond 20 m as the eager one is (views that differ only there embed
    alike, bit for bit)."""
    from navi_learner.engine.encoder import RayViTEncoder

    torch.manual_seed(0)
    dev = torch.device("cuda")
    enc = RayViTEncoder((3, 256, 48), EngineConfig(view_range=0.2)).to(dev).eval()
    compiled = torch.compile(enc)
    n = 512
    depth = (torch.rand(n, 256, 48, device=dev) * 0.4).half().float()  # (N, Az, El) 0-40 m of 100
    before = (torch.rand(n, 256, 48, device=dev) * 0.4).half().float()  # (N, Az, El) the previous frame
    semantic = torch.where(torch.rand(n, 256, 48, device=dev) < 0.1, -0.25, 0.75)  # (N, Az, El) marks
    view = torch.stack([depth, semantic, depth - before], dim=1)  # (N, 3, Az, El)
    far = (depth > 0.25) & (before > 0.25)  # (N, Az, El) beyond 20 m in both frames
    other = view.clone()
    other[:, 0] = torch.where(far, 1.0, depth)  # misses there instead
    other[:, 1] = torch.where(far & (semantic > 0), 0.0, semantic)
    other[:, 2] = torch.where(far, 0.0, view[:, 2])
    with torch.no_grad():
        eager, fused, fused_other = enc(view), compiled(view), compiled(other)  # (N, D) each
    assert torch.allclose(fused, eager, atol=2e-4, rtol=0)
    assert torch.equal(fused, fused_other)


@pytest.mark.parametrize("patch", [(16, 16), (32, 16)], ids=["16x16", "32x16"])
def test_the_patch_token_kernel_is_the_written_out_stage_on_cuda(patch: tuple[int, int]) -> None:
    """The input stage's kernel at the canonical 256 × 48 view, from compact frames (a shuffled minibatch)
    and from the float32 frames they decode to, with and without the view cap: float32 tokens within
    1e-6 of the written-out twin on the GPU (the kernel's log is the fast one inductor uses), bf16 tokens
    within one unit in the last place and nearly all equal, and both entries bit for bit alike."""
    from navi_learner.engine.tokens import (
        compact_patch_tokens_triton,
        gather_frames,
        patch_tokens_ref,
        patch_tokens_triton,
    )

    from .test_learner_tokens import compact_frames

    dev = torch.device("cuda")
    frames = compact_frames(16, 64, 256, 48, 8)
    frames = frames._replace(
        **{k: v.to(dev) for k, v in frames._asdict().items() if isinstance(v, torch.Tensor)}
    )
    obs = gather_frames(*frames).flatten(0, 1)  # (L·M, 3, Az, El) float32: 1,024 frames
    for view_range in (1.0, 0.2):
        ref = patch_tokens_ref(obs, patch, view_range)  # (L·M, P, 4·pa·pe)
        for dtype in (torch.float32, torch.bfloat16):
            got = patch_tokens_triton(obs, patch, view_range, dtype)
            assert torch.equal(compact_patch_tokens_triton(frames, patch, view_range, dtype), got)
            assert got.shape == ref.shape and got.dtype == dtype
            want = ref.to(dtype).float()
            if dtype == torch.float32:
                assert (got - want).abs().max().item() <= 1e-6
            else:
                diff = (got.float() - want).abs()  # (L·M, P, 4·pa·pe)
                assert bool((diff <= want.abs() * 2**-7 + 1e-6).all())
                assert (diff > 0).float().mean().item() < 1e-3


def test_fused_attention_kernels_match_the_reference_on_cuda() -> None:
    """The Triton kernels of short_attention against the written-out float32 reference, in float32 and
    in bf16 (the training path under autocast), at the default 48 tokens × 4 heads of 32."""
    g = torch.Generator(device="cuda").manual_seed(0)
    for dtype, tol in ((torch.float32, 1e-4), (torch.bfloat16, 3e-2)):
        base = torch.randn(512, 48, 3, 4, 32, device="cuda", generator=g)  # (N, P, 3, h, d)
        qkv = base.to(dtype).requires_grad_(True)
        out = short_attention(qkv)  # (N, P, h, d)
        ref = short_attention_ref(qkv.detach().float())  # (N, P, h, d)
        assert out.dtype == dtype and (out.float() - ref).abs().max().item() < tol
        dout = torch.randn(out.shape, device="cuda", generator=g).to(dtype)  # (N, P, h, d)
        (grad,) = torch.autograd.grad(out, qkv, dout)  # (N, P, 3, h, d)
        want = short_attention_backward_ref(qkv.detach().float(), dout.float())  # (N, P, 3, h, d)
        assert grad.dtype == dtype
        assert (grad.float() - want).abs().max().item() < tol * max(1.0, want.abs().max().item())


def test_fused_attention_runs_the_twin_where_the_float32_kernels_do_not_serve() -> None:
    """float32 at 128 tokens of heads 64 wide (beyond FLOAT32_KERNEL_TILE): the operator on CUDA gives
    the written-out attention and its gradient, without compiling the large float32 kernels."""
    g = torch.Generator(device="cuda").manual_seed(2)
    qkv = torch.randn(8, 128, 3, 2, 64, device="cuda", generator=g, requires_grad=True)  # (N, P, 3, h, d)
    assert not kernel_serves(128, 64, torch.float32)
    out = short_attention(qkv)  # (N, P, h, d)
    dout = torch.randn(out.shape, device="cuda", generator=g)  # (N, P, h, d)
    (grad,) = torch.autograd.grad(out, qkv, dout)  # (N, P, 3, h, d)
    assert torch.allclose(out, short_attention_ref(qkv.detach()), atol=1e-6, rtol=0)
    assert torch.allclose(grad, short_attention_backward_ref(qkv.detach(), dout), atol=1e-6, rtol=0)


def test_auto_attention_runs_the_fused_operator_on_cuda() -> None:
    """The default attention (auto) on CUDA is the fused operator: the same numbers, bit for bit."""
    torch.manual_seed(0)
    shape = (3, 256, 48)
    auto = RayViTEncoder(shape, EngineConfig()).cuda()
    fused = RayViTEncoder(shape, EngineConfig(attention="fused")).cuda()
    fused.load_state_dict(auto.state_dict())
    obs = torch.rand(64, *shape, device="cuda")  # (N, 3, Az, El)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        assert torch.equal(auto(obs), fused(obs))


def test_compiled_encoder_with_fused_attention_matches_sdpa_on_cuda() -> None:
    """The encoder compiled as one graph with the fused operator, under bf16 autocast, gives the eager
    SDPA encoder's embedding and gradients (same weights) to bf16 precision."""
    torch.manual_seed(0)
    shape = (3, 256, 48)
    cfg = EngineConfig(attention="sdpa")
    sdpa = RayViTEncoder(shape, cfg).cuda()
    fused = RayViTEncoder(shape, replace(cfg, attention="fused")).cuda()
    fused.load_state_dict(sdpa.state_dict())
    compiled = torch.compile(fused, fullgraph=True, dynamic=False)
    obs = torch.rand(256, *shape, device="cuda")  # (N, 3, Az, El)
    outs, grads = [], []
    for enc in (sdpa, compiled):
        with torch.autocast("cuda", dtype=torch.bfloat16):
            y = enc(obs).float()  # (N, D)
        y.square().mean().backward()
        outs.append(y.detach())
    for a, b in zip(sdpa.parameters(), fused.parameters(), strict=True):
        grads.append(((a.grad - b.grad).abs().max() / a.grad.abs().max().clamp_min(1e-6)).item())  # type: ignore[operator, union-attr]
    assert (outs[0] - outs[1]).abs().max().item() < 3e-2 * outs[0].abs().max().item()
    assert max(grads) < 0.1
