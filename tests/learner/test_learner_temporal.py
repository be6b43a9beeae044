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
    assert torch.allclose(s_fast[0], s_ref[0], atol=1e-5, rtol=0)


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


def test_gradients_flow_through_the_chunked_scan() -> None:
    torch.manual_seed(0)
    core = Mamba2Core(small("mamba2"))
    x, resets = random_inputs(9)
    x.requires_grad_(True)
    y, _ = core(x, resets, core.initial_state(N, torch.device("cpu")))
    y.pow(2).mean().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert core.A_log.grad is not None and core.A_log.grad.abs().sum() > 0


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
