"""The parity test of test_learner_distributed: the real `update()` on each rank's half of a fixed
rollout. Run as a script under torchrun (gloo), it writes rank<r>.pt into the folder it is given; the
test imports the same setup for the single-process update on the whole rollout."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.ppo.dist import Sync, setup, shutdown
from navi_learner.ppo.rollout import RolloutStorage
from navi_learner.ppo.train import update

ENGINE = EngineConfig.tiny()
OBS = (3, 16, 8)
ACTORS, ROLLOUT, CHUNK = 8, 16, 8
CPU = torch.device("cpu")


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
        whether the second update left the replica unchanged, this rank's normalised advantages, and the
    state and rate after a third update with the adaptive rate."""
    torch.set_num_threads(1)
    d, _ = setup("cpu")
    try:
        policy, optimizer, buf, cfg = parity_setup()
        sync = Sync(d, [q for q in policy.parameters() if q.requires_grad], CPU)
        sync.broadcast_module(policy)
        part = shard(buf, d.rank, d.world)
        policy.rnd.intrinsic(embeddings().chunk(d.world)[d.rank], sync.sum_)
        adv = sync.normalize(part.advantages)  # (T, N/W)
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
        result = {
            "state": after,
            "skipped": [skipped, skipped_bad],
            "unchanged": unchanged,
            "adv": adv,
            "adaptive": adaptive,
        }
        torch.save(result, out / f"rank{d.rank}.pt")
        sync.barrier()
    finally:
        shutdown(d)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
