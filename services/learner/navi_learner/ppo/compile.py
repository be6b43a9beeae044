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
from navi_learner.engine.tokens import CompactFrames
from navi_learner.ppo.dist import Collectives, Sync
from navi_learner.ppo.loss import mean_bound_loss, ppo_loss

Forward = Callable[[torch.Tensor, torch.Tensor, CoreState], tuple[ActOut, torch.Tensor, torch.Tensor]]
"""The rollout's policy step: (obs, resets, state) -> (ActOut, RND novelty (N,), loop penalty (N,))."""


def rollout_forward(policy: CognitiveMambaPolicy, memory: EpisodicMemory) -> Forward:
    """The rollout's policy step of one process, eager: the policy's act, the RND novelty of its embedding
    (the normaliser updated) and the episodic memory's loop penalty."""

    def forward(
        obs: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[ActOut, torch.Tensor, torch.Tensor]:
        out = policy.act(obs, resets, state)
        return out, policy.rnd.intrinsic(out.emb), memory.step(out.emb, resets)  # ActOut, (N,), (N,)

    return forward


PooledStep = Callable[
    [torch.Tensor, torch.Tensor, CoreState, torch.Tensor],
    tuple[ActOut, torch.Tensor, torch.Tensor, torch.Tensor],
]
"""A data-parallel rank's policy step: (obs, resets, state, the previous step's normaliser sums pooled
over ranks (3,) float64) -> (ActOut, RND novelty (N,), loop penalty (N,), this step's sums (3,) float64)."""


def pooled_step(policy: CognitiveMambaPolicy, memory: EpisodicMemory) -> PooledStep:
    """A data-parallel rank's policy step without its collective, so it compiles to one graph: act, the RND
    novelty under the normaliser that has folded in the pooled sums it is handed, the loop penalty, and
    this step's own sums for the ranks to pool."""

    def step(
        obs: torch.Tensor, resets: torch.Tensor, state: CoreState, pooled: torch.Tensor
    ) -> tuple[ActOut, torch.Tensor, torch.Tensor, torch.Tensor]:
        out = policy.act(obs, resets, state)
        novelty, sums = policy.rnd.intrinsic_pooled(out.emb, pooled)  # (N,), (3,) float64
        return out, novelty, memory.step(out.emb, resets), sums  # ActOut, (N,), (N,), (3,)

    return step


class PooledForward:
    """The rollout's policy step of a data-parallel rank: its RND normaliser follows every rank's actors,
    one step late (ppo.dist). Each step hands `step` (pooled_step, eager or one compiled graph) the sums
    of the previous step, pooled over ranks and waited for on the device, then launches its own sums'
    all-reduce, which the next step's graph reads: the collective lies between two graphs, never inside
    one. The run's first step has no earlier sums: `step` runs with placeholder sums, the normaliser is
    put back as it was, and the step's own sums, pooled and waited for (Sync.sum_kept), are folded in to
    score its novelty; the second step folds them in once more, as one process's first batch sets its
    normaliser. The same graph serves every step."""

    def __init__(
        self, policy: CognitiveMambaPolicy, memory: EpisodicMemory, sync: Sync, step: PooledStep
    ) -> None:
        self.policy, self.memory, self.sync, self.step = policy, memory, sync, step

    def __call__(
        self, obs: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[ActOut, torch.Tensor, torch.Tensor]:
        pooled = self.sync.lagged_previous()  # (3,) float64, or None at the run's first step
        if pooled is None:
            return self._first(obs, resets, state)
        out, novelty, loop, sums = self.step(obs, resets, state, pooled)  # ActOut, (N,), (N,), (3,)
        self.sync.launch_lagged(sums)
        return out, novelty, loop

    def _first(
        self, obs: torch.Tensor, resets: torch.Tensor, state: CoreState
    ) -> tuple[ActOut, torch.Tensor, torch.Tensor]:
        rnd = self.policy.rnd
        before = [b.clone() for b in rnd.buffers()]  # the normaliser as it was
        placeholder = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=obs.device)  # (3,) float64
        out, _, loop, sums = self.step(obs, resets, state, placeholder)  # ActOut, (N,), (N,), (3,)
        for b, kept in zip(rnd.buffers(), before, strict=True):
            b.copy_(kept)
        novelty, _ = rnd.intrinsic_pooled(out.emb, self.sync.sum_kept(sums))  # (N,): its own sums, waited
        return out, novelty, loop


def compile_graph(
    fn: Callable[..., Any], backend: str = "inductor", fullgraph: bool = True, graphs: bool = False
) -> Callable[..., Any]:
    """`fn` compiled for fixed shapes: one graph (fullgraph), or graphs split where it must (host reads);
    with inductor and `graphs`: replayed as CUDA graphs (torch.compile's reduce-overhead)."""
    if backend != "inductor":
        return torch.compile(fn, fullgraph=fullgraph, dynamic=False, backend=backend)
    options: dict[str, Any] = {"triton.cudagraphs": graphs}
    return torch.compile(fn, fullgraph=fullgraph, dynamic=False, backend=backend, options=options)


def update_graphs(cfg: TrainConfig, device: torch.device) -> bool:
    """The update's compiled objective replays as CUDA graphs: cfg.update_graphs, with its compile, on CUDA,
    where the objective is one graph (not the gru's, which reads episode starts on the host)."""
    return (
        cfg.update_graphs
        and cfg.compile
        and cfg.compile_update
        and device.type == "cuda"
        and cfg.engine.temporal_core != "gru"
    )


def rank_forward(
    policy: CognitiveMambaPolicy,
    memory: EpisodicMemory,
    sync: Collectives | None = None,
    compiled: bool = False,
) -> Forward:
    """The rollout's policy step of this process, eager or `compiled` (one graph: act, RND, memory); on a
    data-parallel rank (`sync` a Sync) the PooledForward around that step, whose normaliser all-reduce
    runs between the steps' graphs."""
    if isinstance(sync, Sync):
        step = pooled_step(policy, memory)
        return PooledForward(
            policy, memory, sync, cast(PooledStep, compile_graph(step)) if compiled else step
        )
    forward = rollout_forward(policy, memory)
    return cast(Forward, compile_graph(forward)) if compiled else forward


def make_forward(
    policy: CognitiveMambaPolicy,
    memory: EpisodicMemory,
    cfg: TrainConfig,
    device: torch.device,
    sync: Collectives | None = None,
) -> Forward:
    """The rollout's policy step for a run (rank_forward): compiled where cfg.compile and
    cfg.compile_rollout ask for it on CUDA, else eager."""
    return rank_forward(policy, memory, sync, cfg.compile and cfg.compile_rollout and device.type == "cuda")


Objective = Callable[..., tuple[torch.Tensor, dict[str, torch.Tensor]]]


def ppo_objective(policy: CognitiveMambaPolicy, cfg: TrainConfig, norm_adv: bool) -> Objective:
    """A minibatch's objective, eager: the policy's sequence pass over its observations (`frames`, float32
    or compact, which the encoder's input stage reads as they are),
    the clipped PPO loss (advantages normalised within the minibatch when `norm_adv`), the penalty on
    action means beyond ±1 (weighted by `mean_bound_coef`; the metrics report the share outside either
    way) and the RND predictor's loss -> (total loss (), detached metrics {name: ()})."""
    p = cfg.ppo

    def objective(
        frames: torch.Tensor | CompactFrames,
        resets: torch.Tensor,
        state: CoreState,
        actions: torch.Tensor,
        logp: torch.Tensor,
        adv: torch.Tensor,
        values: torch.Tensor,
        returns: torch.Tensor,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        ev = policy.evaluate(frames, resets, state, actions)  # (L, M) logp and value, (L·M, D) emb
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
        bound_loss, outside = mean_bound_loss(ev.mean)  # (), () share of means beyond ±1
        if p.mean_bound_coef > 0:
            loss = loss + p.mean_bound_coef * bound_loss
        return loss + p.rnd_coef * rnd_loss, {
            **metrics,
            "rnd_loss": rnd_loss.detach(),
            "mean_outside": outside,
        }

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
    gradient buckets are all-reduced after it rather than while it runs. With cfg.update_graphs the compiled
    graphs replay as CUDA graphs (update_graphs; the update marks each minibatch a step of its own)."""
    fn = ppo_objective(policy, cfg, cfg.ppo.norm_adv and not distributed)
    if cfg.compile and cfg.compile_update and device.type == "cuda":
        fullgraph = cfg.engine.temporal_core != "gru"
        return cast(Objective, compile_graph(fn, fullgraph=fullgraph, graphs=update_graphs(cfg, device)))
    return fn
