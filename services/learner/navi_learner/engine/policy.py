"""CognitiveMambaPolicy: RayViTEncoder → RND → (EpisodicMemory, owned by the rollout) → TemporalCore → heads.

The encoder runs once over the flat (T·N) batch, then the temporal core over (T, N), then the heads
(sample-factory style). `act` is the rollout path (one recurrent step), `evaluate` the PPO path
(a sequence pass with the stored initial state of each BPTT chunk).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from navi_learner.config import EngineConfig
from navi_learner.engine.encoder import RayViTEncoder
from navi_learner.engine.heads import ActorCriticHeads, gaussian_entropy, gaussian_log_prob
from navi_learner.engine.rnd import RND
from navi_learner.engine.temporal import CoreState, TemporalCore, make_core


@dataclass
class ActOut:
    """One rollout step of the policy."""

    action: torch.Tensor  # (N, 4) float32, unclipped sample (or the mean when deterministic)
    logp: torch.Tensor  # (N,) float32
    value: torch.Tensor  # (N,) float32
    emb: torch.Tensor  # (N, D) float32 encoder embedding
    state: CoreState  # the temporal core's state after this step


@dataclass
class EvalOut:
    """Sequence evaluation for the PPO loss."""

    logp: torch.Tensor  # (T, N) float32
    entropy: torch.Tensor  # () float32 (state-independent log-std)
    value: torch.Tensor  # (T, N) float32
    emb: torch.Tensor  # (T·N, D) float32


class CognitiveMambaPolicy(nn.Module):
    """The cognitive engine; architecture fixed by EngineConfig, observation shape (3, Az, El)."""

    def __init__(self, obs_shape: tuple[int, int, int], cfg: EngineConfig) -> None:
        super().__init__()
        self.obs_shape = obs_shape
        self.cfg = cfg
        self.encoder = RayViTEncoder(obs_shape, cfg)
        self.rnd = RND(cfg.embed_dim, cfg.rnd_dim)
        self.core: TemporalCore = make_core(cfg)
        self.heads = ActorCriticHeads(cfg.embed_dim, cfg.head_hidden, cfg.init_log_std)
        self.amp = False

    def initial_state(self, n: int, device: torch.device) -> CoreState:
        """Zero recurrent state for n actors."""
        return self.core.initial_state(n, device)

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        """obs (B, 3, Az, El) -> embedding (B, D) float32; bf16 autocast on CUDA when amp is set."""
        with torch.autocast(obs.device.type, dtype=torch.bfloat16, enabled=self.amp and obs.is_cuda):
            return self.encoder(obs)

    def act(
        self, obs: torch.Tensor, resets: torch.Tensor, state: CoreState, deterministic: bool = False
    ) -> ActOut:
        """Rollout step: obs (N, 3, Az, El), resets (N,) bool (episode starts here) -> ActOut."""
        emb = self.encode(obs)  # (N, D)
        feat, state = self.core.step(emb, resets, state)  # (N, D)
        mean, value = self.heads(feat)  # (N, 4), (N,)
        log_std = self.heads.log_std  # (4,)
        action = mean if deterministic else mean + torch.randn_like(mean) * log_std.exp()  # (N, 4)
        return ActOut(action, gaussian_log_prob(action, mean, log_std), value, emb, state)

    def evaluate(
        self, obs: torch.Tensor, resets: torch.Tensor, state: CoreState, actions: torch.Tensor
    ) -> EvalOut:
        """PPO pass: obs (T, N, 3, Az, El), resets (T, N), state at t=0, actions (T, N, 4) -> EvalOut."""
        t_len, n = obs.shape[:2]
        emb = self.encode(obs.flatten(0, 1))  # (T·N, D)
        feat, _ = self.core(emb.view(t_len, n, -1), resets, state)  # (T, N, D)
        mean, value = self.heads(feat)  # (T, N, 4), (T, N)
        log_std = self.heads.log_std  # (4,)
        return EvalOut(gaussian_log_prob(actions, mean, log_std), gaussian_entropy(log_std), value, emb)
