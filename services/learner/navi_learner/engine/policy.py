"""CognitiveMambaPolicy: RayViTEncoder → RND → (EpisodicMemory, owned by the rollout) → TemporalCore → heads.

The encoder runs once over the flat (T·N) batch, then the temporal core over (T, N), then the heads
(sample-factory style). `act` is the rollout path (one recurrent step), `evaluate` the PPO path
(a sequence pass with the stored initial state of each BPTT chunk).

With EngineConfig.action_input the core's input is the embedding plus an embedding of the previous
action, and the state is the core's state followed by that action (N, 4): the rollout stores it with
the core's, so each BPTT chunk starts from the action that preceded it.
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
from navi_learner.engine.tokens import CompactFrames, frames_device

ACTION_DIM = 4
"""[forward, vertical, lateral, yaw_rate] (navi_env.sim.physics)."""


@dataclass
class ActOut:
    """One rollout step of the policy."""

    action: torch.Tensor  # (N, 4) float32, unclipped sample (or the mean when deterministic)
    logp: torch.Tensor  # (N,) float32
    value: torch.Tensor  # (N,) float32
    emb: torch.Tensor  # (N, D) float32 encoder embedding
    state: CoreState  # the temporal core's state after this step
    mean: torch.Tensor  # (N, 4) float32 action mean, before the env's clip


@dataclass
class EvalOut:
    """Sequence evaluation for the PPO loss."""

    logp: torch.Tensor  # (T, N) float32
    entropy: torch.Tensor  # () float32 (state-independent log-std)
    value: torch.Tensor  # (T, N) float32
    emb: torch.Tensor  # (T·N, D) float32
    mean: torch.Tensor  # (T, N, 4) float32 action means, before the env's clip


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
        self.action_embed: nn.Linear | None = None
        if cfg.action_input:
            self.action_embed = nn.Linear(ACTION_DIM, cfg.embed_dim)
            nn.init.zeros_(self.action_embed.weight)  # a fresh engine acts as one without the input
            nn.init.zeros_(self.action_embed.bias)
        self.amp = False

    def initial_state(self, n: int, device: torch.device) -> CoreState:
        """Zero recurrent state for n actors (and a zero previous action with action_input)."""
        state = self.core.initial_state(n, device)
        if self.action_embed is None:
            return state
        return (*state, torch.zeros(n, ACTION_DIM, device=device))  # (N, 4) previous action

    def _split(self, state: CoreState) -> tuple[CoreState, torch.Tensor | None]:
        """The core's part of a state and the previous action (N, 4) (None without action_input)."""
        if self.action_embed is None:
            return state, None
        return state[:-1], state[-1]

    def core_input(
        self, emb: torch.Tensor, previous: torch.Tensor | None, resets: torch.Tensor
    ) -> torch.Tensor:
        """The temporal core's input: the embedding (..., D), plus with action_input the embedding of the
        previous action (..., 4) clipped to [-1, 1] and zeroed where resets (...) marks an episode start."""
        if self.action_embed is None or previous is None:
            return emb
        prev = previous.clamp(-1.0, 1.0) * ~resets[..., None]  # (..., 4)
        return emb + self.action_embed(prev)  # (..., D)

    def encode(self, obs: torch.Tensor | CompactFrames) -> torch.Tensor:
        """obs (B, 3, Az, El), or a compact minibatch of B = L·M frames -> embedding (B, D) float32; bf16
        autocast on CUDA when amp is set."""
        device = frames_device(obs)
        amp = self.amp and device.type == "cuda"
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            return self.encoder(obs, torch.bfloat16 if amp else None)

    def act(
        self,
        obs: torch.Tensor,
        resets: torch.Tensor,
        state: CoreState,
        deterministic: bool = False,
        noise: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> ActOut:
        """Rollout step: obs (N, 3, Az, El), resets (N,) bool (episode starts here) -> ActOut. The action is
        the mean when deterministic, else the mean plus Gaussian noise of `noise` times the learned std
        (training samples at 1; an evaluation may fly another spread), drawn from `generator` where given
        (an evaluation's own stream) or torch's default one."""
        emb = self.encode(obs)  # (N, D)
        core_state, previous = self._split(state)
        feat, core_state = self.core.step(
            self.core_input(emb, previous, resets), resets, core_state
        )  # (N, D)
        mean, value = self.heads(feat)  # (N, 4), (N,)
        log_std = self.heads.log_std  # (4,)
        if deterministic:
            action = mean  # (N, 4)
        else:
            std = log_std.exp() if noise == 1.0 else log_std.exp() * noise  # (4,)
            eps = (
                torch.randn_like(mean)
                if generator is None
                else torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
            )  # (N, 4)
            action = mean + eps * std  # (N, 4)
        if previous is not None:
            core_state = (*core_state, action.detach().clamp(-1.0, 1.0))  # (N, 4) what the env flies
        return ActOut(action, gaussian_log_prob(action, mean, log_std), value, emb, core_state, mean)

    def sequence(
        self, obs: torch.Tensor | CompactFrames, resets: torch.Tensor, state: CoreState, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, CoreState]:
        """Core features over a sequence: obs (T, N, 3, Az, El) (or compact frames of T steps of N
        sequences), resets (T, N), state at t=0, the actions taken (T, N, 4) -> features (T, N, D),
        embedding (T·N, D) and the state after step T-1."""
        t_len, n = resets.shape
        emb = self.encode(obs if isinstance(obs, CompactFrames) else obs.flatten(0, 1))  # (T·N, D)
        core_state, first = self._split(state)
        x = emb.view(t_len, n, -1)  # (T, N, D)
        if first is not None:
            previous = torch.cat((first[None], actions[:-1]), dim=0)  # (T, N, 4) the action before each step
            x = self.core_input(x, previous, resets)  # (T, N, D)
        feat, core_state = self.core(x, resets, core_state)  # (T, N, D)
        if first is not None:
            core_state = (*core_state, actions[-1].detach().clamp(-1.0, 1.0))  # (N, 4)
        return feat, emb, core_state

    def evaluate(
        self, obs: torch.Tensor | CompactFrames, resets: torch.Tensor, state: CoreState, actions: torch.Tensor
    ) -> EvalOut:
        """PPO pass: obs (T, N, 3, Az, El) or compact frames, resets (T, N), state at t=0, actions (T, N, 4)
        -> EvalOut."""
        feat, emb, _ = self.sequence(obs, resets, state, actions)  # (T, N, D), (T·N, D)
        mean, value = self.heads(feat)  # (T, N, 4), (T, N)
        log_std = self.heads.log_std  # (4,)
        return EvalOut(gaussian_log_prob(actions, mean, log_std), gaussian_entropy(log_std), value, emb, mean)
