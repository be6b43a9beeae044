"""GAE: the blocked implementation equals the plain loop, and both match closed-form cases."""

from __future__ import annotations

import pytest
import torch

from navi_learner.ppo.gae import bootstrap_truncated, gae, gae_ref


@pytest.mark.parametrize(
    ("t_len", "n", "block"), [(37, 5, 8), (64, 3, 32), (5, 2, 32), (512, 4, 32), (33, 2, 1)]
)
def test_gae_matches_reference_loop(t_len: int, n: int, block: int) -> None:
    g = torch.Generator().manual_seed(t_len)
    r, v = torch.randn(t_len, n, generator=g), torch.randn(t_len, n, generator=g)
    ends = torch.rand(t_len, n, generator=g) < 0.1
    nv = torch.randn(n, generator=g)
    a1, r1 = gae(r, v, ends, nv, 0.99, 0.95, block)
    a2, r2 = gae_ref(r, v, ends, nv, 0.99, 0.95)
    assert torch.allclose(a1, a2, atol=1e-5)
    assert torch.allclose(r1, r2, atol=1e-5)


def test_gae_analytic_discounted_sum() -> None:
    """λ = 1, V = 0, reward 1 each step, no end, bootstrap 0: A_t = Σ_{k<T-t} γ^k = (1-γ^(T-t))/(1-γ)."""
    t_len, gamma = 10, 0.9
    r, v = torch.ones(t_len, 1), torch.zeros(t_len, 1)
    adv, ret = gae(r, v, torch.zeros(t_len, 1, dtype=torch.bool), torch.zeros(1), gamma, 1.0, block=4)
    expect = torch.tensor([(1 - gamma ** (t_len - t)) / (1 - gamma) for t in range(t_len)])[:, None]
    assert torch.allclose(adv, expect, atol=1e-5)
    assert torch.allclose(ret, expect, atol=1e-5)


def test_gae_episode_end_cuts_bootstrap() -> None:
    """An end after step 2 of 4: steps 0-2 see only rewards up to step 2; step 3 bootstraps next_value."""
    gamma, lam = 0.5, 1.0
    r = torch.tensor([[1.0], [1.0], [1.0], [1.0]])
    v = torch.zeros(4, 1)
    ends = torch.tensor([[False], [False], [True], [False]])
    adv, _ = gae(r, v, ends, torch.tensor([2.0]), gamma, lam)
    assert torch.allclose(adv[:, 0], torch.tensor([1.75, 1.5, 1.0, 2.0]))


def test_bootstrap_truncated_adds_discounted_value_only_on_truncation() -> None:
    r = torch.tensor([[1.0, 1.0]])
    v = torch.tensor([[4.0, 4.0]])
    out = bootstrap_truncated(r, v, torch.tensor([[True, False]]), 0.5)
    assert torch.equal(out, torch.tensor([[3.0, 1.0]]))
