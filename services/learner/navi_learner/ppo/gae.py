"""Generalised advantage estimation: a blocked, loop-light `gae` and the plain `gae_ref` loop.

Conventions (all (T, N) float32 unless said): `ends[t]` is True when the episode ended after step t
(terminated or truncated), which cuts the bootstrap chain. Truncation bootstrapping: the protocol
auto-resets truncated actors, so the final observation is not available; `bootstrap_truncated`
approximates V(s_final) by V(s_t), the value of the last observation seen, and adds γ·V(s_t) to the
reward of the truncated step. Terminations get no bootstrap.
"""

from __future__ import annotations

import torch


def bootstrap_truncated(
    rewards: torch.Tensor, values: torch.Tensor, truncated: torch.Tensor, gamma: float
) -> torch.Tensor:
    """rewards + γ·V(s_t) where the episode was truncated (not terminated) after step t; (T, N)."""
    return rewards + gamma * values * truncated.to(values.dtype)


def gae_ref(
    rewards: torch.Tensor,
    values: torch.Tensor,
    ends: torch.Tensor,
    next_value: torch.Tensor,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The textbook backward loop. rewards/values/ends (T, N), next_value (N,) -> (advantages, returns)."""
    adv = torch.zeros_like(rewards)  # (T, N)
    last = torch.zeros_like(next_value)  # (N,)
    for t in reversed(range(rewards.shape[0])):
        nonterminal = 1.0 - ends[t].to(rewards.dtype)  # (N,)
        nv = next_value if t == rewards.shape[0] - 1 else values[t + 1]  # (N,)
        delta = rewards[t] + gamma * nv * nonterminal - values[t]  # (N,)
        last = delta + gamma * lam * nonterminal * last  # (N,)
        adv[t] = last
    return adv, adv + values


def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    ends: torch.Tensor,
    next_value: torch.Tensor,
    gamma: float,
    lam: float,
    block: int = 32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Same result as gae_ref; the recurrence is solved in blocks of `block` steps by one batched
    matrix product each (A_t = Σ_k (γλ)^(k-t)·[no end in t..k-1]·δ_k), with a loop over blocks only."""
    t_len = rewards.shape[0]
    nonterminal = 1.0 - ends.to(rewards.dtype)  # (T, N)
    next_values = torch.cat([values[1:], next_value[None]], dim=0)  # (T, N)
    delta = rewards + gamma * next_values * nonterminal - values  # (T, N)
    adv = torch.empty_like(rewards)  # (T, N)
    carry = torch.zeros_like(next_value)  # (N,) advantage at the start of the following block
    gl = gamma * lam
    for t1 in range(t_len, 0, -block):
        t0 = max(0, t1 - block)
        length = t1 - t0
        seg = torch.cumsum(ends[t0:t1].long(), dim=0) - ends[t0:t1].long()  # (L, N) ends before k
        idx = torch.arange(length, device=rewards.device)  # (L,)
        gap = idx[None, :] - idx[:, None]  # (L_t, L_k) = k - t
        same = seg.t()[:, None, :] == seg.t()[:, :, None]  # (N, L_t, L_k) no end in t..k-1
        w = (gl ** gap.clamp(min=0).to(rewards.dtype)) * (gap >= 0) * same  # (N, L_t, L_k)
        local = torch.bmm(w, delta[t0:t1].t()[:, :, None])[..., 0]  # (N, L)
        reach = (
            (gl ** (length - idx).to(rewards.dtype))[None, :]
            * (seg.t() == seg.t()[:, -1:])
            * nonterminal[t1 - 1][:, None]
        )  # (N, L) weight of the next block's first advantage
        adv[t0:t1] = (local + reach * carry[:, None]).t()
        carry = adv[t0]
    return adv, adv + values
