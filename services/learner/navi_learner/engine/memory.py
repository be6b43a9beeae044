"""EpisodicMemory: per-actor ring buffer of recent embeddings and a loop-revisitation penalty.

Buffer (N, K, D) of unit-norm embeddings, a validity mask (N, K) and a write pointer (N,): inserting
overwrites the oldest slot (constant-time eviction, no rebuild); an episode start clears an actor's
slots through a mask. Everything is batched over actors (no Python loop over actors).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


class EpisodicMemory:
    """Cosine-similarity memory of the last K embeddings of each actor's current episode."""

    def __init__(self, n_actors: int, slots: int, dim: int, threshold: float, device: torch.device) -> None:
        self.slots = slots
        self.threshold = threshold
        self.keys = torch.zeros(n_actors, slots, dim, device=device)  # (N, K, D) float32 unit vectors
        self.valid = torch.zeros(n_actors, slots, dtype=torch.bool, device=device)  # (N, K) bool
        self.ptr = torch.zeros(n_actors, dtype=torch.long, device=device)  # (N,) int64 next slot
        self.rows = torch.arange(n_actors, device=device)  # (N,) int64

    def reset(self, mask: torch.Tensor) -> None:
        """Clear the actors where mask (N,) bool is set (episode start)."""
        self.valid &= ~mask[:, None]
        self.ptr.masked_fill_(mask, 0)

    def similarity(self, emb: torch.Tensor) -> torch.Tensor:
        """Max cosine similarity (N,) of emb (N, D) to the stored keys; -1 where an actor has none."""
        q = F.normalize(emb.float(), dim=-1)  # (N, D)
        sim = torch.einsum("nkd,nd->nk", self.keys, q)  # (N, K)
        return sim.masked_fill(~self.valid, -1.0).amax(dim=1)  # (N,)

    def insert(self, emb: torch.Tensor) -> None:
        """Write emb (N, D) into each actor's oldest slot and advance the pointer."""
        self.keys[self.rows, self.ptr] = F.normalize(emb.float(), dim=-1)
        self.valid[self.rows, self.ptr] = True
        self.ptr.add_(1).remainder_(self.slots)

    def penalty(self, sim: torch.Tensor) -> torch.Tensor:
        """Loop penalty (N,) in [0, 1]: 0 below the threshold, linear up to 1 at similarity 1."""
        return ((sim - self.threshold) / (1.0 - self.threshold)).clamp(0.0, 1.0)  # (N,)

    def step(self, emb: torch.Tensor, episode_start: torch.Tensor) -> torch.Tensor:
        """Reset finished actors, score emb (N, D) against the memory, insert it; returns the penalty (N,)."""
        self.reset(episode_start)
        pen = self.penalty(self.similarity(emb))  # (N,)
        self.insert(emb)
        return pen


def episodic_step_ref(
    history: list[list[torch.Tensor]],
    emb: torch.Tensor,
    episode_start: torch.Tensor,
    slots: int,
    threshold: float,
) -> torch.Tensor:
    """Plain per-actor twin of EpisodicMemory.step over Python lists (history[i] = actor i's keys)."""
    out = []
    for i in range(emb.shape[0]):
        if bool(episode_start[i]):
            history[i].clear()
        q = F.normalize(emb[i].float(), dim=0)  # (D,)
        best = max((float(torch.dot(k, q)) for k in history[i]), default=-1.0)
        out.append(min(max((best - threshold) / (1.0 - threshold), 0.0), 1.0))
        history[i].append(q)
        if len(history[i]) > slots:
            history[i].pop(0)
    return torch.tensor(out)  # (N,) float32
