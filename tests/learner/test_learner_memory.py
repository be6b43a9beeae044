"""EpisodicMemory: ring-buffer eviction, reset at episode start, parity with a per-actor list twin."""

from __future__ import annotations

import torch

from navi_learner.engine.memory import EpisodicMemory, episodic_step_ref


def test_matches_reference_under_random_resets() -> None:
    g = torch.Generator().manual_seed(0)
    n, k, d = 5, 4, 8
    mem = EpisodicMemory(n, k, d, threshold=0.5, device=torch.device("cpu"))
    history: list[list[torch.Tensor]] = [[] for _ in range(n)]
    base = torch.randn(3, d, generator=g)  # a few recurring "places" so similarities are high
    for t in range(40):
        emb = base[torch.randint(0, 3, (n,), generator=g)] + 0.1 * torch.randn(n, d, generator=g)  # (N, D)
        start = (torch.rand(n, generator=g) < 0.15) | (t == 0)  # (N,) bool
        fast = mem.step(emb, start)
        ref = episodic_step_ref(history, emb, start, k, 0.5)
        assert torch.allclose(fast, ref, atol=1e-5), t


def test_eviction_is_oldest_first_and_reset_clears() -> None:
    d = 4
    eye = torch.eye(d)
    mem = EpisodicMemory(1, 2, d, threshold=0.5, device=torch.device("cpu"))
    no = torch.zeros(1, dtype=torch.bool)
    mem.step(eye[0:1], no)
    mem.step(eye[1:2], no)
    assert mem.similarity(eye[0:1]).item() == 1.0  # still stored
    mem.step(eye[2:3], no)  # evicts e0 (the oldest), keeps e1, e2
    assert mem.similarity(eye[0:1]).item() == 0.0
    assert mem.similarity(eye[1:2]).item() == 1.0
    assert int(mem.ptr[0]) == 1  # write pointer wrapped
    pen = mem.step(eye[1:2], torch.ones(1, dtype=torch.bool))  # episode start: memory cleared first
    assert pen.item() == 0.0
    assert int(mem.valid.sum()) == 1


def test_penalty_ramps_from_threshold() -> None:
    mem = EpisodicMemory(1, 4, 2, threshold=0.8, device=torch.device("cpu"))
    assert torch.allclose(mem.penalty(torch.tensor([0.5, 0.8, 0.9, 1.0])), torch.tensor([0.0, 0.0, 0.5, 1.0]))
