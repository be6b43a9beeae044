"""Temporal cores: the recurrent step loop equals the sequence pass under random episode resets."""

from __future__ import annotations

import copy

import pytest
import torch

from navi_learner.config import EngineConfig
from navi_learner.engine.temporal import GRUCore, Mamba2Core, MambaPyCore, make_core

T, N, D = 45, 6, 32


def small(core: str) -> EngineConfig:
    return EngineConfig(embed_dim=D, ssm_head_dim=16, ssm_chunk=8, gru_hidden=24, temporal_core=core)  # type: ignore[arg-type]


def random_inputs(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(T, N, D, generator=g)  # (T, N, D)
    resets = torch.rand(T, N, generator=g) < 0.12  # (T, N) bool
    return x, resets


def random_state(core: Mamba2Core | GRUCore, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    return tuple(torch.randn(s.shape, generator=g) for s in core.initial_state(N, torch.device("cpu")))


def step_loop(
    core: Mamba2Core | GRUCore, x: torch.Tensor, resets: torch.Tensor, state: tuple[torch.Tensor, ...]
):
    ys = []
    for t in range(x.shape[0]):
        y, state = core.step(x[t], resets[t], state)
        ys.append(y)
    return torch.stack(ys), state


@pytest.mark.parametrize("name", ["mamba2", "gru", "mambapy"])
def test_step_loop_equals_sequence_pass_with_random_resets(name: str) -> None:
    torch.manual_seed(0)
    core = make_core(small(name))
    x, resets = random_inputs(1)
    state = random_state(core, 2)
    with torch.no_grad():
        y_seq, s_seq = core(x, resets, state)
        y_step, s_step = step_loop(core, x, resets, state)
    assert torch.allclose(y_seq, y_step, atol=1e-5, rtol=0)
    for a, b in zip(s_seq, s_step, strict=True):
        assert torch.allclose(a, b, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["mamba2", "gru"])
def test_sequence_pass_carries_state_across_calls(name: str) -> None:
    torch.manual_seed(0)
    core = make_core(small(name))
    x, resets = random_inputs(3)
    state = random_state(core, 4)
    with torch.no_grad():
        y_all, _ = core(x, resets, state)
        y1, mid = core(x[:19], resets[:19], state)
        y2, _ = core(x[19:], resets[19:], mid)
    assert torch.allclose(y_all, torch.cat([y1, y2]), atol=1e-5, rtol=0)


def test_chunked_scan_matches_plain_mambapy_reference() -> None:
    torch.manual_seed(0)
    fast = Mamba2Core(small("mamba2"))
    ref = MambaPyCore(small("mambapy"))
    ref.load_state_dict(fast.state_dict())
    x, resets = random_inputs(5)
    state = random_state(fast, 6)
    with torch.no_grad():
        y_fast, s_fast = fast(x, resets, state)
        y_ref, s_ref = ref(x, resets, state)
    assert torch.allclose(y_fast, y_ref, atol=1e-5, rtol=0)
    assert len(s_fast) == len(s_ref) >= 2  # the SSM state and the convolution window
    for a, b in zip(s_fast, s_ref, strict=True):
        assert torch.allclose(a, b, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["mamba2", "gru"])
def test_reset_forgets_everything_before_it(name: str) -> None:
    """After a reset at t=10, outputs equal a fresh run started at t=10 from the zero state."""
    torch.manual_seed(0)
    core = make_core(small(name))
    x, _ = random_inputs(7)
    resets = torch.zeros(T, N, dtype=torch.bool)
    resets[10] = True
    with torch.no_grad():
        y, _ = core(x, resets, random_state(core, 8))
        fresh, _ = core(
            x[10:], torch.zeros(T - 10, N, dtype=torch.bool), core.initial_state(N, torch.device("cpu"))
        )
    assert torch.allclose(y[10:], fresh, atol=1e-5, rtol=0)
    assert not torch.allclose(y[:10], fresh[:10], atol=1e-3)


def test_chunked_scan_gradients_match_the_plain_reference() -> None:
    """In float64, the gradients of one loss through the chunked scan and through the plain recurrence of
    the same weights agree for the input, the starting state and every parameter, to 1e-9 of each
    gradient's own largest entry (float64 rounding over a 45-step sequence is far below that)."""
    torch.manual_seed(0)
    fast = Mamba2Core(small("mamba2")).double()
    ref = MambaPyCore(small("mambapy")).double()
    ref.load_state_dict(fast.state_dict())
    x, resets = random_inputs(9)
    state = random_state(fast, 10)
    grads = []
    for core in (fast, ref):
        xi = x.double().requires_grad_(True)
        si = tuple(s.double().requires_grad_(True) for s in state)
        y, out = core(xi, resets, si)
        (y.pow(2).mean() + sum(o.pow(2).mean() for o in out)).backward()
        named = {f"param {k}": p.grad for k, p in core.named_parameters()}
        named |= {"input": xi.grad, **{f"state {i}": s.grad for i, s in enumerate(si)}}
        grads.append(named)
    assert grads[0].keys() == grads[1].keys()
    for key, g_ref in grads[1].items():
        g_fast = grads[0][key]
        assert g_fast is not None and g_ref is not None, key
        scale = float(g_ref.abs().max())
        assert scale > 0, key  # every input, state and parameter takes part in the loss
        assert float((g_fast - g_ref).abs().max()) <= 1e-9 * scale, key


def test_gru_step_follows_weights_loaded_copied_and_converted() -> None:
    """The written-out GRU step reads nn.GRU's own parameters: after load_state_dict, deepcopy and a
    dtype conversion it still equals the (nn.GRU) sequence pass of the module it belongs to."""
    torch.manual_seed(0)
    core, other = GRUCore(small("gru")), GRUCore(small("gru"))
    core.load_state_dict(other.state_dict())
    core = copy.deepcopy(core).double()
    x, resets = random_inputs(7)
    state = tuple(s.double() for s in random_state(core, 8))
    with torch.no_grad():
        y_seq, s_seq = core(x.double(), resets, state)
        y_step, s_step = step_loop(core, x.double(), resets, state)
        y_other, _ = other(x, resets, tuple(s.float() for s in state))
    assert y_step.dtype == torch.float64
    assert torch.allclose(y_seq, y_step, atol=1e-10, rtol=0)
    assert torch.allclose(s_seq[0], s_step[0], atol=1e-10, rtol=0)
    assert torch.allclose(y_step.float(), y_other, atol=1e-5, rtol=0)
