"""The parity tests of test_learner_distributed: the real `update()` on each rank's half of a fixed
rollout (gradients in several buckets), the bucketed gradient average against one flat all-reduce of all
gradients (eager and compiled objective), and the one-step-late RND normaliser. Run as a script under
torchrun (gloo), it writes rank<r>.pt into the folder it is given; the test imports the same setup for
the single-process references."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch
import torch.distributed as tdist

from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.engine.rnd import RND
from navi_learner.ppo.compile import Objective, compile_graph, ppo_objective, rank_forward
from navi_learner.ppo.dist import Bucket, Dist, Sync, setup, shutdown
from navi_learner.ppo.rollout import RolloutStorage
from navi_learner.ppo.train import update

ENGINE = EngineConfig.tiny()
OBS = (3, 16, 8)
ACTORS, ROLLOUT, CHUNK = 8, 16, 8
CPU = torch.device("cpu")
SMALL_BUCKET_MB = 0.02  # the tiny engine's 95 kB of gradients in 5 buckets
BUCKET_SIZES = {"one bucket": 25.0, "a few": SMALL_BUCKET_MB, "one per parameter": 1e-6}
LAGGED_STEPS = 5


def parity_setup() -> tuple[CognitiveMambaPolicy, torch.optim.Optimizer, RolloutStorage, TrainConfig]:
    """The same policy, optimizer and 8-actor rollout in every process (fixed seeds)."""
    torch.manual_seed(0)
    policy = CognitiveMambaPolicy(OBS, ENGINE)
    optimizer = torch.optim.Adam([q for q in policy.parameters() if q.requires_grad], lr=1e-3, eps=1e-5)
    ppo = PPOConfig(num_minibatches=1, ppo_epochs=1, bptt_chunk=CHUNK)
    cfg = TrainConfig(n_actors=ACTORS, rollout_length=ROLLOUT, engine=ENGINE, ppo=ppo)
    buf = RolloutStorage(ROLLOUT, ACTORS, OBS, policy.initial_state(ACTORS, CPU), CHUNK, CPU)
    g = torch.Generator().manual_seed(1)
    buf.obs.copy_(torch.rand(buf.obs.shape, generator=g))  # (T, N, 3, Az, El)
    buf.actions.copy_(torch.randn(buf.actions.shape, generator=g))  # (T, N, 4)
    buf.logp.copy_(torch.randn(buf.logp.shape, generator=g) - 4.0)  # (T, N)
    buf.values.copy_(torch.randn(buf.values.shape, generator=g))  # (T, N)
    buf.advantages.copy_(torch.randn(buf.advantages.shape, generator=g) * 3 + 1)  # (T, N)
    buf.returns.copy_(torch.randn(buf.returns.shape, generator=g))  # (T, N)
    buf.resets.copy_(torch.rand(buf.resets.shape, generator=g) < 0.1)  # (T, N) bool
    for s in buf.states:
        s.copy_(torch.randn(s.shape, generator=g) * 0.1)  # (T/L, N, ...)
    return policy, optimizer, buf, cfg


def embeddings() -> torch.Tensor:
    """A fixed batch of 16 embeddings for the RND normaliser."""
    return torch.randn(16, ENGINE.embed_dim, generator=torch.Generator().manual_seed(7))  # (16, D)


def step_observations() -> torch.Tensor:
    """LAGGED_STEPS env steps of 16 actors' observations, each step's spread different."""
    g = torch.Generator().manual_seed(11)
    scale = torch.linspace(0.5, 2.0, LAGGED_STEPS).reshape(-1, 1, 1, 1, 1)  # (K, 1, 1, 1, 1)
    return torch.rand(LAGGED_STEPS, 16, *OBS, generator=g) * scale  # (K, 16, 3, Az, El)


def lagged_rollout(d: Dist, sync: Sync) -> dict[str, Any]:
    """LAGGED_STEPS steps of this rank's share of 16 actors through the rollout step a rank trains with
    (rank_forward: the eager PooledForward), from the parity policy: the novelty and the embeddings of
    each step, the RND state it started from and the normaliser at the end."""
    policy = parity_setup()[0]
    start = {k: v.clone() for k, v in policy.rnd.state_dict().items()}
    n = 16 // d.world
    memory = EpisodicMemory(n, ENGINE.memory_slots, ENGINE.embed_dim, ENGINE.memory_threshold, CPU)
    forward = rank_forward(policy, memory, sync)
    state, resets = policy.initial_state(n, CPU), torch.ones(n, dtype=torch.bool)  # (N/W,) bool
    novelty, emb = [], []
    with torch.no_grad():
        for obs in step_observations():  # (16, 3, Az, El)
            out, nov, _ = forward(obs.chunk(d.world)[d.rank], resets, state)  # ActOut, (N/W,), (N/W,)
            novelty.append(nov)
            emb.append(out.emb)
            state, resets = out.state, torch.zeros_like(resets)
    sync.settle()
    return {
        "novelty": torch.stack(novelty),  # (K, N/W)
        "emb": torch.stack(emb),  # (K, N/W, D)
        "start": start,
        "normaliser": dict(policy.rnd.named_buffers()),
    }


def fresh_rnd() -> RND:
    """The parity policy's RND (the same weights in every process), its normaliser not yet started."""
    return parity_setup()[0].rnd


def flat_average(params: list[torch.nn.Parameter], world: int) -> list[torch.Tensor]:
    """The reference: every gradient in one flat buffer, one all-reduce, ÷ world; a copy per parameter."""
    grads = [torch.zeros(p.numel()) if p.grad is None else p.grad.reshape(-1) for p in params]  # (numel_i,)
    flat = torch.cat(grads)  # (P,) float32
    tdist.all_reduce(flat)
    flat.div_(world)
    return [g.view_as(p) for g, p in zip(flat.split([p.numel() for p in params]), params, strict=True)]


def record_sends(sync: Sync, first: torch.nn.Parameter) -> list[bool]:
    """From now on, for every bucket `sync` launches: whether it went while backward still ran and had
    not yet reached `first` (the first registered parameter, the last one backward reaches)."""
    early: list[bool] = []
    send = sync._send

    def sending(bucket: Bucket) -> None:
        early.append(sync.armed and first.grad is None)
        send(bucket)

    sync._send = sending  # type: ignore[method-assign]
    return early


def bucket_parity(d: Dist, part: RolloutStorage, compiled: bool) -> dict[str, tuple[int, int, bool]]:
    """For each of BUCKET_SIZES: (number of buckets, how many of them were launched while backward had
    not yet reached the first parameter, whether Sync.backward's averaged gradients equal flat_average's
    bit for bit) on this rank's minibatch, with the eager or the compiled objective."""
    policy, _, _, cfg = parity_setup()
    params = [q for q in policy.parameters() if q.requires_grad]
    objective: Objective = ppo_objective(policy, cfg, False)
    if compiled:  # AOTAutograd's one backward graph, as on CUDA (inductor there)
        objective = compile_graph(objective, backend="aot_eager")
    (mb,) = part.minibatches(1, torch.Generator().manual_seed(0))

    def loss() -> torch.Tensor:
        for q in params:
            q.grad = None
        return objective(
            mb.obs, mb.resets, mb.state, mb.actions, mb.logp, mb.advantages, mb.values, mb.returns
        )[0]

    loss().backward()
    want = flat_average(params, d.world)
    out = {}
    for name, mb_size in BUCKET_SIZES.items():
        sync = Sync(d, params, CPU, bucket_mb=mb_size)
        early = record_sends(sync, params[0])
        bad = sync.backward(loss())
        got = [q.grad for q in params]
        same = not bool(bad) and all(
            g is not None and torch.equal(g, w) for g, w in zip(got, want, strict=True)
        )
        out[name] = (len(sync.buckets), sum(early), same)
        sync.release()
    return out


def shard(buf: RolloutStorage, rank: int, world: int) -> RolloutStorage:
    """Actors [rank·N/W, (rank+1)·N/W) of a rollout as a storage of their own."""
    n = buf.n // world
    lo = rank * n
    template = tuple(s[0, :n] for s in buf.states)  # each (N/W, ...)
    part = RolloutStorage(buf.t_len, n, OBS, template, buf.chunk, CPU)
    for name in (
        "obs",
        "actions",
        "logp",
        "values",
        "rewards",
        "resets",
        "ends",
        "truncs",
        "advantages",
        "returns",
    ):
        getattr(part, name).copy_(getattr(buf, name)[:, lo : lo + n])
    for dst, src in zip(part.states, buf.states, strict=True):
        dst.copy_(src[:, lo : lo + n])
    return part


def main(out: Path) -> None:
    """This rank: RND normaliser and advantages pooled over ranks, one clean update, then one update in
    which rank 1's loss alone is non-finite; writes the state after the clean update, the skip counts,
    whether the second update left the replica unchanged, this rank's normalised advantages, the state
    and rate after a third update with the adaptive rate, the bucket parities, and the novelty and
    normaliser of LAGGED_STEPS rollout steps whose RND normaliser is pooled one step late."""
    torch.set_num_threads(1)
    d, _ = setup("cpu")
    try:
        policy, optimizer, buf, cfg = parity_setup()
        sync = Sync(d, [q for q in policy.parameters() if q.requires_grad], CPU, bucket_mb=SMALL_BUCKET_MB)
        sync.broadcast_module(policy)
        part = shard(buf, d.rank, d.world)
        policy.rnd.intrinsic(embeddings().chunk(d.world)[d.rank], sync.sum_)
        ids = part.minibatch_ids(2, torch.Generator().manual_seed(4))  # (2, M): this rank's 2 minibatches
        adv = {"ids": ids, "moments": sync.advantage_moments(part.advantages, ids, part.chunk)}  # (2, 2)
        _, skipped = update(policy, optimizer, part, cfg, torch.Generator().manual_seed(d.rank), None, sync)
        after = {k: v.clone() for k, v in policy.state_dict().items()}
        if d.rank == 1:
            part.advantages[0, 0] = float("nan")
        _, skipped_bad = update(
            policy, optimizer, part, cfg, torch.Generator().manual_seed(d.rank), None, sync
        )
        unchanged = all(torch.equal(after[k], v) for k, v in policy.state_dict().items())
        part.advantages[0, 0] = 0.0
        cfg.ppo.target_kl = 0.01  # the adaptive rate: one rank-mean KL decides every rank's rate
        for group in optimizer.param_groups:
            group["lr"] = torch.tensor(float(group["lr"]))
        update(policy, optimizer, part, cfg, torch.Generator().manual_seed(d.rank), None, sync)
        adaptive = {"state": policy.state_dict(), "lr": float(optimizer.param_groups[0]["lr"])}
        lagged = lagged_rollout(d, sync)
        result = {
            "state": after,
            "skipped": [skipped, skipped_bad],
            "unchanged": unchanged,
            "adv": adv,
            "adaptive": adaptive,
            "buckets": len(sync.buckets),
            "bucket_parity": {
                "eager": bucket_parity(d, part, False),
                "compiled": bucket_parity(d, part, True),
            },
            "lagged": lagged,
        }
        torch.save(result, out / f"rank{d.rank}.pt")
        sync.barrier()
    finally:
        shutdown(d)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
