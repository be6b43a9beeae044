"""Rollout storage (T, N, ...) allocated once on the training device, and sequence-aware minibatches.

Step t stores the observation the policy acted on, its action, log-prob and value, the reward of the
transition, `resets[t]` (an episode starts at t: the recurrent state and episodic memory were zeroed
before acting), `ends[t]` and `truncs[t]` (the episode ended after step t). The recurrent state that
entered step t is stored at every BPTT chunk start, so each (chunk, actor) sequence can be replayed
independently with truncated BPTT.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch

from navi_learner.heads import ACTION_DIM
from navi_learner.temporal import CoreState


@dataclass
class Minibatch:
    """M whole sequences of length L (time-major)."""

    obs: torch.Tensor  # (L, M, 3, Az, El) storage dtype
    actions: torch.Tensor  # (L, M, 4) float32
    logp: torch.Tensor  # (L, M) float32
    values: torch.Tensor  # (L, M) float32
    advantages: torch.Tensor  # (L, M) float32
    returns: torch.Tensor  # (L, M) float32
    resets: torch.Tensor  # (L, M) bool
    state: CoreState  # each (M, ...) float32: the recurrent state entering the first step


class RolloutStorage:
    """Preallocated (T, N, ...) buffers on one device."""

    def __init__(
        self,
        t_len: int,
        n: int,
        obs_shape: tuple[int, int, int],
        obs_dtype: torch.dtype,
        state_template: CoreState,
        bptt_chunk: int,
        device: torch.device,
    ) -> None:
        if t_len % bptt_chunk:
            raise ValueError(f"rollout length {t_len} is not a multiple of the BPTT chunk {bptt_chunk}")
        self.t_len, self.n, self.chunk = t_len, n, bptt_chunk
        self.n_chunks = t_len // bptt_chunk
        self.obs = torch.zeros(t_len, n, *obs_shape, dtype=obs_dtype, device=device)  # (T, N, 3, Az, El)
        self.actions = torch.zeros(t_len, n, ACTION_DIM, device=device)  # (T, N, 4) float32
        self.logp = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.values = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.rewards = torch.zeros(t_len, n, device=device)  # (T, N) float32 extrinsic + intrinsic
        self.resets = torch.zeros(t_len, n, dtype=torch.bool, device=device)  # (T, N) bool
        self.ends = torch.zeros(t_len, n, dtype=torch.bool, device=device)  # (T, N) bool
        self.truncs = torch.zeros(t_len, n, dtype=torch.bool, device=device)  # (T, N) bool
        self.advantages = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.returns = torch.zeros(t_len, n, device=device)  # (T, N) float32
        self.states = tuple(
            torch.zeros(self.n_chunks, *s.shape, dtype=s.dtype, device=device) for s in state_template
        )  # each (T/L, N, ...)

    def store_state(self, t: int, state: CoreState) -> None:
        """Keep the recurrent state entering step t when t starts a BPTT chunk."""
        if t % self.chunk == 0:
            for buf, s in zip(self.states, state, strict=True):
                buf[t // self.chunk].copy_(s)

    def minibatches(
        self, num_minibatches: int, generator: torch.Generator | None = None
    ) -> Iterator[Minibatch]:
        """Shuffle the (chunk, actor) sequences and yield num_minibatches groups of whole sequences."""
        total = self.n_chunks * self.n
        device = self.obs.device
        perm = torch.randperm(total, generator=generator).to(device)  # (S,) int64 sequence ids
        size = max(1, total // num_minibatches)
        for start in range(0, total - size + 1, size):
            ids = perm[start : start + size]  # (M,)
            c, a = ids // self.n, ids % self.n  # (M,) each

            def seq(buf: torch.Tensor, c: torch.Tensor = c, a: torch.Tensor = a) -> torch.Tensor:
                view = buf.view(self.n_chunks, self.chunk, self.n, *buf.shape[2:])  # (T/L, L, N, ...)
                return view[c, :, a].transpose(0, 1)  # (L, M, ...)

            yield Minibatch(
                obs=seq(self.obs),
                actions=seq(self.actions),
                logp=seq(self.logp),
                values=seq(self.values),
                advantages=seq(self.advantages),
                returns=seq(self.returns),
                resets=seq(self.resets),
                state=tuple(s[c, a] for s in self.states),
            )
