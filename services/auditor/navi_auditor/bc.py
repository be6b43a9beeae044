"""`navi bc`: behavioural cloning of CognitiveMambaPolicy from demonstrations, with truncated BPTT.

Data: every demonstration (time order, files by name) is laid end to end into one timeline; an episode
start resets the recurrent state. The timeline is cut into N equal streams (N = `streams`), giving
obs (L, N, 3, Az, El), actions (L, N, 4) and resets (L, N). An epoch walks the streams in chunks of
`bptt` steps, carrying the recurrent state (detached) from chunk to chunk, exactly like PPO's BPTT.

Loss: mean squared error between the policy mean and the demonstrated action. The Gaussian's log-std is
left as initialised so that an RL fine-tune starts with its usual exploration.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from navi_auditor.demos import Demo
from navi_learner.config import EngineConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState


@dataclass(frozen=True)
class BCConfig:
    """Behavioural-cloning run."""

    epochs: int = 20
    """Passes over the demonstrations."""
    bptt: int = 32
    """Truncated-BPTT chunk length (steps); the recurrent state is carried, detached, between chunks."""
    streams: int = 8
    """N: parallel sequences the timeline is cut into (the batch of every chunk)."""
    lr: float = 5e-4
    """Adam learning rate."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip."""
    seed: int = 0
    """Seed for the weights."""
    device: str = "cpu"
    """Torch device string."""


@dataclass(frozen=True)
class Sequences:
    """Demonstrations as N parallel streams of L steps."""

    obs: torch.Tensor  # (L, N, 3, Az, El) float32
    actions: torch.Tensor  # (L, N, 4) float32
    resets: torch.Tensor  # (L, N) bool, True where an episode starts


def to_sequences(demos: list[Demo], streams: int, device: torch.device) -> Sequences:
    """Lay the demonstrations end to end and cut the timeline into `streams` equal streams."""
    obs = np.concatenate([d.observations for d in demos]).astype(np.float32)  # (T, 3, Az, El)
    actions = np.concatenate([d.actions for d in demos])  # (T, 4)
    resets = np.concatenate([d.episode_starts for d in demos])  # (T,) bool
    total = actions.shape[0]
    n = max(1, min(streams, total))
    length = total // n
    cut = length * n

    def split(a: np.ndarray) -> torch.Tensor:
        shaped = a[:cut].reshape(n, length, *a.shape[1:]).swapaxes(0, 1)  # (L, N, ...)
        return torch.from_numpy(np.ascontiguousarray(shaped)).to(device)

    seq_resets = split(resets)  # (L, N) bool
    seq_resets[0] = True  # every stream starts from a fresh state
    return Sequences(split(obs), split(actions), seq_resets)


def _detach(state: CoreState) -> CoreState:
    return tuple(s.detach() for s in state)


def policy_mean(
    policy: CognitiveMambaPolicy,
    obs: torch.Tensor,
    resets: torch.Tensor,
    state: CoreState,
    actions: torch.Tensor,
) -> tuple[torch.Tensor, CoreState]:
    """Action mean over a sequence: obs (T, N, 3, Az, El), resets (T, N), the demonstrated actions (T, N, 4)
    (an engine with action_input reads each step's predecessor) -> (T, N, 4) and the final state."""
    feat, _, state = policy.sequence(obs, resets, state, actions)  # (T, N, D)
    mean, _ = policy.heads(feat)  # (T, N, 4)
    return mean, state


def bc_loss(mean: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Mean squared error between policy means (T, N, 4) and demonstrated actions (T, N, 4): a scalar."""
    return (mean - actions).pow(2).mean()


def train_bc(
    demos: list[Demo],
    engine: EngineConfig,
    config: BCConfig,
    on_epoch: Callable[[int, float], None] | None = None,
) -> tuple[CognitiveMambaPolicy, list[float]]:
    """Clone the demonstrations; returns the policy and the mean loss of every epoch."""
    torch.manual_seed(config.seed)
    device = torch.device(config.device)
    data = to_sequences(demos, config.streams, device)
    policy = CognitiveMambaPolicy(demos[0].obs_shape, engine).to(device)
    optimizer = torch.optim.Adam(policy.parameters(), lr=config.lr)
    length, n = data.resets.shape
    losses: list[float] = []
    for epoch in range(config.epochs):
        state = policy.initial_state(n, device)
        total, count = 0.0, 0
        for start in range(0, length, config.bptt):
            end = min(start + config.bptt, length)
            mean, state = policy_mean(
                policy, data.obs[start:end], data.resets[start:end], state, data.actions[start:end]
            )
            loss = bc_loss(mean, data.actions[start:end])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), config.max_grad_norm)
            optimizer.step()
            state = _detach(state)
            total += float(loss.detach()) * (end - start)
            count += end - start
        losses.append(total / count)
        if on_epoch is not None:
            on_epoch(epoch, losses[-1])
    return policy, losses


@torch.no_grad()
def action_error(policy: CognitiveMambaPolicy, demos: list[Demo], device: torch.device) -> float:
    """Mean squared error of the deterministic policy against the demonstrated actions (one stream each)."""
    errors, steps = 0.0, 0
    for demo in demos:
        data = to_sequences([demo], 1, device)
        mean, _ = policy_mean(policy, data.obs, data.resets, policy.initial_state(1, device), data.actions)
        errors += float(bc_loss(mean.clamp(-1.0, 1.0), data.actions)) * demo.steps
        steps += demo.steps
    return errors / steps


def run_bc(
    demos: list[Demo],
    out: Path,
    engine: EngineConfig,
    config: BCConfig,
    on_epoch: Callable[[int, float], None] | None = None,
) -> dict[str, float | str]:
    """Train, then write a v3 checkpoint with training_source="bc"; returns a summary."""
    started = time.monotonic()
    policy, losses = train_bc(demos, engine, config, on_epoch)
    save_bc_checkpoint(out, policy, demos, engine, config, (time.monotonic() - started) / 3600.0)
    return {
        "checkpoint": str(out),
        "first_loss": losses[0],
        "final_loss": losses[-1],
        "demonstrations": float(len(demos)),
        "steps": float(sum(d.steps for d in demos)),
        "epochs": float(config.epochs),
        "wall_s": time.monotonic() - started,
    }


def save_bc_checkpoint(
    out: Path,
    policy: CognitiveMambaPolicy,
    demos: list[Demo],
    engine: EngineConfig,
    config: BCConfig,
    wall_hours: float,
) -> Path:
    """Write the cloned policy as a learner v3 checkpoint.

    training_source="bc", no parent, step and episode counts 0 (no environment steps were trained),
    reward_ema the demonstrations' mean reward per step, no optimizer state (the RL fine-tune starts its
    own optimizer). `navi train --checkpoint OUT` resumes from it and records it as its parent.
    """
    from navi_learner.config import TrainConfig
    from navi_learner.ppo.runs import new_run_id
    from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint

    rewards = np.concatenate([d.rewards for d in demos])  # (T,) float32
    meta = CheckpointMeta(
        step_id=0,
        episode_count=0,
        reward_ema=float(rewards.mean()),
        wall_time_hours=wall_hours,
        temporal_core=engine.temporal_core,
        run_id=f"bc-{new_run_id()}",
        config=TrainConfig(engine=engine, device=config.device, seed=config.seed).to_dict(),
        obs_shape=list(demos[0].obs_shape),
        parent_checkpoint=None,
        training_source="bc",
        corpus_summary={
            "demonstrations": [str(d.path) for d in demos],
            "scenes": sorted({d.scene for d in demos}),
            "steps": int(rewards.shape[0]),
            "bc_epochs": config.epochs,
            "bc_bptt": config.bptt,
        },
    )
    return save_checkpoint(out, policy.state_dict(), None, meta)
