"""The PPO training loop (CleanRL-style) and its three stages: collect (one rollout), learn (advantages,
then the PPO update) and report (a log line; at the end the final checkpoint, promotion and the report).
The loop reads the same on one rank and on N: every cross-rank step goes through the run's collectives
(ppo.dist: Sync on several ranks, its twin Solo on one).

Intrinsic rewards are functions of the observed state: step t's reward is the env reward plus
w_rnd·RND(e_t) − w_ep·loop_penalty(e_t), with e_t the embedding the policy acted on.

Beside it: the run's learner and its setup (learner.py), the policy steps, eager or compiled
(compile.py), stage timers and the training clock (timing.py), promotion into the registry (promotion.py).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch

from navi_learner.config import TrainConfig
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState
from navi_learner.envs.protocol import BatchedEnv
from navi_learner.ppo.compile import Forward, Objective, ppo_objective, rank_forward, update_graphs
from navi_learner.ppo.dist import Collectives, Dist, Solo, Sync, write_debug
from navi_learner.ppo.gae import bootstrap_truncated, gae
from navi_learner.ppo.learner import Learner, first_carry, setup
from navi_learner.ppo.promotion import promote
from navi_learner.ppo.rollout import RolloutStorage
from navi_learner.ppo.runs import Progress, write_report
from navi_learner.ppo.stats import EpisodeStats
from navi_learner.ppo.timing import Clock, StageTimers
from navi_learner.serving.registry import ModelRegistry


class Monitor(Protocol):
    """Called after every PPO update with the live policy; returns True to end training there.

    `status` is a short line for the progress bar. The loop does not count the time a call takes as
    training time (train_s excludes it, and SPS windows skip it)."""

    status: str

    def __call__(self, policy: CognitiveMambaPolicy, step_id: int, train_s: float) -> bool: ...


@dataclass
class TrainResult:
    """What a finished (or interrupted) run leaves behind."""

    run_id: str
    run_dir: Path
    final_checkpoint: Path
    report: Path
    step_id: int
    episode_count: int
    reward_ema: float
    sps: float
    skipped_updates: int
    interrupted: bool
    config: TrainConfig
    """The run's resolved settings (config.resolve: its actors, rollout length, learning rate...)."""
    promoted: str | None = None
    last_metrics: dict[str, float] = field(default_factory=dict)


def collect(
    policy: CognitiveMambaPolicy,
    env: BatchedEnv,
    buf: RolloutStorage,
    memory: EpisodicMemory,
    stats: EpisodeStats,
    cfg: TrainConfig,
    carry: tuple[torch.Tensor, torch.Tensor, CoreState],
    timers: StageTimers,
    sync: Collectives | None = None,
    check_storage: bool = False,
    forward: Forward | None = None,
) -> tuple[tuple[torch.Tensor, torch.Tensor, CoreState], torch.Tensor]:
    """Fill the storage with one rollout; returns the new (obs, resets, state) carry and the mean
    extrinsic reward per actor-step (a device scalar). With `sync` a Sync (several ranks) the RND
    normaliser follows every rank's actors (3 numbers all-reduced per step, folded in one step later:
    compile.PooledForward). With `check_storage` (a
    run's first rollout) the stored form of step 1's observation is compared with what the policy saw
    (one host read). `forward` is the rollout's policy step (default: the eager `rank_forward`;
    `make_forward` compiles it)."""
    sync = sync or Solo(env.device)
    forward = forward or rank_forward(policy, memory, sync)
    obs, resets, state = carry
    ext_sum = torch.zeros((), device=env.device)  # () float32
    buf.begin()
    for t in range(buf.t_len):
        with timers("forward"), torch.no_grad():
            buf.store_state(t, state)
            out, novelty, loop = forward(obs, resets, state)  # ActOut, (N,) RND novelty, (N,) loop penalty
            intrinsic = cfg.ppo.intrinsic_rnd_weight * novelty - cfg.ppo.intrinsic_episodic_weight * loop
            buf.resets[t].copy_(resets)
            buf.store_obs(t, obs)
            if check_storage and t == 1:  # once per run: the stored form gives back what the policy saw
                check_storage = False
                if not torch.equal(buf.obs_at(t), obs):
                    raise ValueError(
                        "the env's observations do not survive compact storage (it sets compact_obs but "
                        "they are not DistanceMatrix v2 as navi_env.sim.observation writes them): "
                        "train with --obs-storage float32 (obs_dtype float32)"
                    )
            buf.actions[t].copy_(out.action)
            buf.logp[t].copy_(out.logp)
            buf.values[t].copy_(out.value)
            state = out.state
        with timers("env"):
            step = env.step(out.action)
        with timers("forward"):
            ends = step.done | step.truncated  # (N,) bool
            buf.rewards[t].copy_(step.reward + intrinsic)
            buf.ends[t].copy_(ends)
            buf.truncs[t].copy_(step.truncated & ~step.done)
            ext_sum += step.reward.sum()
            stats.update(step, intrinsic)
            obs, resets = step.obs, ends
    return (obs, resets, state), ext_sum / (buf.t_len * buf.n)


def advantages(
    policy: CognitiveMambaPolicy,
    buf: RolloutStorage,
    cfg: TrainConfig,
    carry: tuple[torch.Tensor, torch.Tensor, CoreState],
) -> None:
    """GAE over the rollout into buf.advantages / buf.returns, bootstrapping from the next observation."""
    obs, resets, state = carry
    with torch.no_grad():
        next_value = policy.act(obs, resets, state, deterministic=True).value  # (N,)
        rewards = bootstrap_truncated(buf.rewards, buf.values, buf.truncs, cfg.ppo.gamma)  # (T, N)
        adv, ret = gae(rewards, buf.values, buf.ends, next_value, cfg.ppo.gamma, cfg.ppo.gae_lambda)
    buf.advantages.copy_(adv)
    buf.returns.copy_(ret)


def adapt_lr(optimizer: torch.optim.Optimizer, kl: torch.Tensor, target: float, lo: float, hi: float) -> None:
    """The KL rule of massively parallel PPO, on the device: every group's rate (a () tensor) ÷1.5 where
    `kl` > 2·target, ×1.5 where `kl` < target/2, kept within [lo, hi]. A non-finite `kl` leaves it."""
    factor = torch.where(kl > 2 * target, 1 / 1.5, torch.where(kl < target / 2, 1.5, 1.0))  # () float32
    for group in optimizer.param_groups:
        lr = group["lr"]  # () float32 on the device (setup made it a tensor)
        lr.copy_((lr * factor).clamp(lo, hi))


def update(
    policy: CognitiveMambaPolicy,
    optimizer: torch.optim.Optimizer,
    buf: RolloutStorage,
    cfg: TrainConfig,
    gen: torch.Generator,
    logger: logging.Logger | None = None,
    sync: Collectives | None = None,
    objective: Objective | None = None,
) -> tuple[dict[str, torch.Tensor], int]:
    """PPO epochs over sequence minibatches. A non-finite loss or gradient norm skips that optimizer
    step and is counted. With a fused optimizer (the learner's on CUDA) the skip happens on the device
    (`found_inf`) and the count is read once per update, so the host never waits for a minibatch;
    otherwise one host read per minibatch decides. Returns mean metrics (device) and the skip count.

    With `sync` a Sync (a data-parallel run, equal minibatches on every rank) the advantages are normalised
    over the union of the ranks' minibatches and the gradients averaged over ranks before clipping (bucketed
    all-reduces launched during backward, the last one carrying the non-finite-loss flags too): a step on W
    ranks is a single-process step on the union, and every rank takes the same skip decision.

    `objective` (make_objective; default the eager one) computes each minibatch's loss and metrics."""
    p = cfg.ppo
    params = [q for q in policy.parameters() if q.requires_grad]
    sync = sync or Solo(params[0].device)
    objective = objective or ppo_objective(policy, cfg, p.norm_adv and not sync.pools_advantages)
    sums: dict[str, torch.Tensor] = {}
    count, skipped = 0, 0
    on_device = bool(optimizer.defaults.get("fused"))  # the optimizer skips a step itself on found_inf
    skips = torch.zeros((), device=params[0].device)  # () float32, steps skipped on the device
    graphs = update_graphs(cfg, params[0].device)  # the objective replays CUDA graphs: one step each
    if graphs and buf.compact:  # the graphs read the compact frames where they lie, never a copy
        for frames in (buf.depth16, buf.semantic, buf.table):
            torch._dynamo.mark_static_address(frames, guard=False)
    for _ in range(p.ppo_epochs):
        ids = buf.minibatch_ids(p.num_minibatches, gen)  # (K, M) sequences per minibatch
        pooled = None  # (K, 2) mean and std of each minibatch's advantages over all ranks
        if isinstance(sync, Sync) and p.norm_adv:
            pooled = sync.advantage_moments(buf.advantages, ids, buf.chunk)
        for i, mb_ids in enumerate(ids):
            mb = buf.minibatch(mb_ids)
            adv = mb.advantages  # (L, M)
            if pooled is not None:
                adv = (mb.advantages - pooled[i, 0]) / (pooled[i, 1] + 1e-8)  # (L, M) over all ranks
            if graphs:  # the last minibatch's graph outputs are spent (its gradients were stepped)
                torch.compiler.cudagraph_mark_step_begin()
            total, metrics = objective(
                mb.frames, mb.resets, mb.state, mb.actions, mb.logp, adv, mb.values, mb.returns
            )  # (), {name: ()}
            if p.target_kl > 0:
                kl = sync.mean({"kl": metrics["approx_kl"]})["kl"]  # () over all ranks
                adapt_lr(optimizer, kl, p.target_kl, p.lr_min, p.lr_max)
            optimizer.zero_grad(set_to_none=True)
            some_loss_bad = sync.backward(total)  # () bool, the same on every rank
            grad_norm = torch.nn.utils.clip_grad_norm_(params, p.max_grad_norm)
            ok = ~some_loss_bad & torch.isfinite(grad_norm)  # () bool
            if on_device:  # no host read: a fused optimizer leaves its state alone where found_inf is 1
                bad = (~ok).float()  # () float32
                optimizer.found_inf = bad  # type: ignore[attr-defined]
                optimizer.step()
                skips += bad
            elif bool(ok):
                optimizer.step()
            else:
                skipped += 1
                if logger is not None:
                    logger.warning("non-finite loss or gradient: optimizer step skipped")
            optimizer.zero_grad(set_to_none=True)
            extra = {"grad_norm": grad_norm.detach()}
            if p.target_kl > 0:
                extra["lr"] = optimizer.param_groups[0]["lr"].clone()  # () the rate of this step
            for k, v in {**metrics, **extra}.items():
                sums[k] = sums.get(k, torch.zeros((), device=v.device)) + v  # () float32
            count += 1
    if on_device:
        optimizer.found_inf = None  # type: ignore[attr-defined]
        skipped = int(skips)  # one host read per update
        if skipped and logger is not None:
            logger.warning(f"non-finite loss or gradient: {skipped} optimizer step(s) skipped")
    means = {k: v / max(count, 1) for k, v in sums.items()}
    if "lr" not in means:  # a constant rate: one () tensor per update
        means["lr"] = torch.full((), float(optimizer.param_groups[0]["lr"]), device=skips.device)
    return means, skipped


def log_row(
    lrn: Learner, clock: Clock, metrics: dict[str, torch.Tensor], bar: Progress, status: str
) -> dict[str, float]:
    """One log line: counters, SPS, the update's metrics (averaged over ranks), episode statistics and
    ms per stage; written to the run's metrics and shown on the progress bar."""
    steps_window = clock.steps_window
    sps = clock.window_sps()
    lrn.sync_counters(clock)
    st, sync, d = lrn.state, lrn.sync, lrn.dist
    metrics = sync.mean(metrics)  # averaged over ranks
    row = {
        "step": float(st.step_id),
        "train_s": clock.train_s(),
        "sps": sps,
        "reward_ema": st.reward_ema,
        "episode_count": float(st.episode_count),
        "skipped_updates": float(st.skipped_updates),
        **{k: float(v) for k, v in metrics.items()},
        **lrn.stats.read(sync.reduce),
        **lrn.timers.read(steps_window // (lrn.buf.n * d.world)),
    }
    lrn.run.log_metrics(row)
    bar.update(st.step_id, sps, clock.train_s(), f"reward_ema {st.reward_ema:+.3f} {status}".rstrip())
    return row


def finish(
    lrn: Learner,
    clock: Clock,
    start_step: int,
    registry: ModelRegistry | None,
    interrupted: bool,
    stopped: bool,
    row: dict[str, float],
) -> TrainResult:
    """The final checkpoint, promotion into the registry (rank 0, a run not interrupted), the report."""
    st, cfg, d, sync, run = lrn.state, lrn.cfg, lrn.dist, lrn.sync, lrn.run
    latest = lrn.checkpoint(clock)
    elapsed = time.perf_counter() - clock.t_start
    sps_total = (st.step_id - start_step) / max(elapsed, 1e-9)
    promoted = None
    if registry is not None and not interrupted and d.main and latest.is_file():
        promoted = promote(registry, latest, run, cfg.engine.temporal_core)
    summary = {
        "run_id": run.run_id,
        "steps": st.step_id,
        "episodes": st.episode_count,
        "reward_ema": f"{st.reward_ema:.4f}",
        "mean SPS": f"{sps_total:,.0f}",
        "skipped updates": st.skipped_updates,
        "final checkpoint": latest,
        "interrupted": interrupted,
        "stopped early": stopped and st.step_id < cfg.total_steps,
        "training seconds": f"{clock.train_s():.1f}",
        "promoted": promoted or "no",
        "temporal core": cfg.engine.temporal_core,
        "actors": cfg.n_actors,
        "rollout length": cfg.rollout_length,
        "device": str(lrn.env.device),
    }
    if d.active:
        summary["ranks"] = d.world
    report = write_report(run, summary)
    run.logger.info(f"done: {summary}")
    write_debug(d, lrn.policy, lrn.optimizer, st.step_id)
    sync.barrier()  # no rank leaves before rank 0's checkpoint and report are on disk
    run.close()
    return TrainResult(
        run.run_id,
        run.root,
        latest,
        report,
        st.step_id,
        st.episode_count,
        st.reward_ema,
        sps_total,
        st.skipped_updates,
        interrupted,
        cfg,
        promoted,
        row,
    )


def train(
    env: BatchedEnv,
    cfg: TrainConfig,
    *,
    run_dir: Path | None = None,
    resume_from: Path | None = None,
    on_log: Callable[[str, dict[str, float]], None] | None = None,
    registry: ModelRegistry | None = None,
    corpus_summary: dict[str, Any] | None = None,
    run_id: str | None = None,
    progress: bool | None = None,
    monitor: Monitor | None = None,
    dist: Dist | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> TrainResult:
    """Train until cfg.total_steps, cfg.time_limit_s of training time, the monitor says stop (final
    checkpoint each time), or Ctrl+C (checkpoint first, then return).

    `should_stop` is polled once per update and ends the run like Ctrl+C. With `dist` (a rank of a
    data-parallel run, dist.py) every rank calls this with its own env of cfg.n_actors actors; the
    ranks agree on stopping once per update, steps count every rank's actors, and rank 0 alone writes
    (checkpoints, metrics, TensorBoard, manifest, report, registry) and runs the monitor."""
    d = dist or Dist()
    lrn = setup(
        env, cfg, run_dir=run_dir, run_id=run_id, resume_from=resume_from, on_log=on_log,
        corpus_summary=corpus_summary, dist=d,
    )  # fmt: skip
    cfg, st, sync, policy, buf = lrn.cfg, lrn.state, lrn.sync, lrn.policy, lrn.buf
    monitor = monitor if d.main else None
    carry = first_carry(lrn)
    bar = Progress(cfg.total_steps, progress if d.main else False, cfg.time_limit_s)
    per_update = buf.t_len * buf.n * d.world  # env steps of one update, all ranks
    start_step, clock = st.step_id, Clock()
    next_ckpt = (st.step_id // cfg.checkpoint_every + 1) * cfg.checkpoint_every
    row: dict[str, float] = {}
    updates = 0
    interrupted, stopped = False, False
    try:
        while st.step_id < cfg.total_steps and not stopped and not interrupted:
            # collect: one rollout of T steps for every actor, the policy in inference mode
            policy.eval()
            carry, ext_mean = collect(
                policy,
                env,
                buf,
                lrn.memory,
                lrn.stats,
                cfg,
                carry,
                lrn.timers,
                sync,
                check_storage=updates == 0,
                forward=lrn.forward,
            )
            # advantages, then the PPO update
            with lrn.timers("learn"):
                advantages(policy, buf, cfg, carry)
                policy.train()
                metrics, skipped = update(
                    policy, lrn.optimizer, buf, cfg, lrn.gen, lrn.run.logger, sync, lrn.objective
                )
            st.skipped_updates += skipped
            st.step_id += per_update
            clock.steps_window += per_update
            updates += 1
            # stop? the monitor (its time is not training time), the time budget, a signal; ranks agree
            if monitor is not None:
                t_call = time.perf_counter()
                stopped = monitor(policy, st.step_id, clock.train_s())
                clock.pause(time.perf_counter() - t_call)
            # the budget by rank 0's clock: only it leaves the monitor's time out (the others wait then)
            if cfg.time_limit_s > 0 and d.main and clock.train_s() >= cfg.time_limit_s:
                stopped = True
            if should_stop is not None and should_stop():
                interrupted = True
                lrn.run.logger.warning("stop requested: saving a checkpoint")
            interrupted, stopped, ext_mean = sync.agree(interrupted, stopped, ext_mean)  # any rank's
            lrn.track_reward(ext_mean)
            # log
            if updates % cfg.log_every == 0 or st.step_id >= cfg.total_steps or stopped:
                row = log_row(lrn, clock, metrics, bar, monitor.status if monitor is not None else "")
            # checkpoint
            if st.step_id >= next_ckpt and st.step_id < cfg.total_steps and not (stopped or interrupted):
                lrn.checkpoint(clock)
                next_ckpt += cfg.checkpoint_every
    except KeyboardInterrupt:
        if d.active:
            raise  # mid-collective: this rank cannot checkpoint with the others (signals set a flag instead)
        interrupted = True
        lrn.run.logger.warning("interrupted: saving a checkpoint")
    bar.close()
    return finish(lrn, clock, start_step, registry, interrupted, stopped, row)
