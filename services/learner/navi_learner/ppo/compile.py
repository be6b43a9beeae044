"""The policy steps a run calls in its hot loops, eager or compiled for fixed shapes: the rollout's
step (act, RND novelty, loop penalty: make_forward) and the update's minibatch objective (the policy's
sequence pass, the PPO loss and the RND loss, with its backward: make_objective)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import torch

from navi_learner.config import TrainConfig
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.policy import ActOut, CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState
from navi_learner.ppo.loss import ppo_loss

Forward = Callable[[torch.Tensor, torch.Tensor, CoreState], tuple[ActOut, torch.Tensor, torch.Tensor]]
"""The rollout's policy step: (obs, resets, state) -> (ActOut, RND novelty (N,), loop penalty (N,))."""


def rollout_forward(
    policy: CognitiveMambaPolicy,
    memory: EpisodicMemory,
    act: Callable[..., ActOut] | None = None,
    reduce: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> Forward:
    """The rollout's policy step, eager: `act` (default policy.act), the RND novelty of its embedding
    (the normaliser updated; `reduce` pools it over ranks) and the episodic memory's loop penalty."""

    def forward(
        obs: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[ActOut, torch.Tensor, torch.Tensor]:
        out = (act or policy.act)(obs, resets, state)
        return out, policy.rnd.intrinsic(out.emb, reduce), memory.step(out.emb, resets)  # ActOut, (N,), (N,)

    return forward


def compile_graph(
    fn: Callable[..., Any], backend: str = "inductor", fullgraph: bool = True
) -> Callable[..., Any]:
    """`fn` compiled for fixed shapes: one graph (fullgraph), or graphs split where it must (host reads)."""
    return torch.compile(fn, fullgraph=fullgraph, dynamic=False, backend=backend)


def make_forward(
    policy: CognitiveMambaPolicy,
    memory: EpisodicMemory,
    cfg: TrainConfig,
    device: torch.device,
    reduce: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> Forward:
    """The rollout's policy step for a run: eager unless cfg.compile and cfg.compile_rollout ask for it on
    CUDA; then one graph (act, RND, memory), or, where `reduce` pools the RND normaliser over ranks (a
    collective the graph cannot hold), the compiled act with RND and memory eager."""
    if not (cfg.compile and cfg.compile_rollout and device.type == "cuda"):
        return rollout_forward(policy, memory, reduce=reduce)
    if reduce is None:
        return cast(Forward, compile_graph(rollout_forward(policy, memory)))
    return rollout_forward(policy, memory, act=compile_graph(policy.act), reduce=reduce)


Objective = Callable[..., tuple[torch.Tensor, dict[str, torch.Tensor]]]


def ppo_objective(policy: CognitiveMambaPolicy, cfg: TrainConfig, norm_adv: bool) -> Objective:
    """A minibatch's objective, eager: the policy's sequence pass, the clipped PPO loss (advantages
    normalised within the minibatch when `norm_adv`) and the RND predictor's loss ->
    (total loss (), detached metrics {name: ()})."""
    p = cfg.ppo

    def objective(
        obs: torch.Tensor,
        resets: torch.Tensor,
        state: CoreState,
        actions: torch.Tensor,
        logp: torch.Tensor,
        adv: torch.Tensor,
        values: torch.Tensor,
        returns: torch.Tensor,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        ev = policy.evaluate(obs, resets, state, actions)  # (L, M) logp and value, (L·M, D) emb
        loss, metrics = ppo_loss(
            ev.logp,
            logp,
            adv,
            ev.value,
            values,
            returns,
            ev.entropy,
            clip_coef=p.clip_coef,
            value_clip_coef=p.value_clip_coef,
            vf_coef=p.vf_coef,
            ent_coef=p.ent_coef,
            norm_adv=norm_adv,
        )
        rnd_loss = policy.rnd.loss(ev.emb)  # ()
        return loss + p.rnd_coef * rnd_loss, {**metrics, "rnd_loss": rnd_loss.detach()}

    return objective


def make_objective(
    policy: CognitiveMambaPolicy, cfg: TrainConfig, device: torch.device, distributed: bool
) -> Objective:
    """The PPO update's minibatch objective for a run: eager unless cfg.compile and cfg.compile_update ask
    for it compiled on CUDA, its backward with it: one graph with mamba2; the gru's sequence pass reads
    where episodes start on the host, which splits its graph there. Data-parallel runs normalise the
    advantages over the ranks before the objective (a collective the graph cannot hold) and average the
    gradients through hooks on the parameters while the update calls backward (ppo.dist.Sync.backward):
    the compiled backward, one graph (a few with gru), hands the hooks every gradient at its end, so the
    gradient buckets are all-reduced after it rather than while it runs."""
    fn = ppo_objective(policy, cfg, cfg.ppo.norm_adv and not distributed)
    if cfg.compile and cfg.compile_update and device.type == "cuda":
        return cast(Objective, compile_graph(fn, fullgraph=cfg.engine.temporal_core != "gru"))
    return fn
