"""The PPO training loop (CleanRL-style: collect → advantages → update → log), in-process with the env.

Intrinsic rewards are functions of the observed state: step t's reward is the env reward plus
w_rnd·RND(e_t) − w_ep·loop_penalty(e_t), with e_t the embedding the policy acted on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol, cast

import torch

from navi_learner.config import TrainConfig, compact_storage, resolve
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.policy import ActOut, CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState
from navi_learner.envs.protocol import BatchedEnv
from navi_learner.ppo.dist import Dist, Sync, write_debug
from navi_learner.ppo.gae import bootstrap_truncated, gae
from navi_learner.ppo.loss import ppo_loss
from navi_learner.ppo.rollout import RolloutStorage
from navi_learner.ppo.runs import Progress, RunFiles, new_run_id, write_report
from navi_learner.ppo.stats import EpisodeStats
from navi_learner.serving.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    checkpoint_name,
    count_write_error,
    load_checkpoint,
    newest_good_checkpoint,
    os_reason,
    prune_checkpoints,
    save_checkpoint,
)
from navi_learner.serving.registry import ModelRegistry

log = logging.getLogger(__name__)
STAGES = ("env", "forward", "learn")
"""The stages a step's time is split into (they do not overlap)."""
TIMED = (*STAGES, "sync")
"""What StageTimers reports: the stages, and "sync", the time a data-parallel run spends in its collectives
(ppo.dist.Sync): mostly the rollout's per-step normaliser sum and each minibatch's normalisation and
gradient all-reduces, which lie within forward and learn, plus a few per update and per log line. Timed by
CUDA events, a collective's time is its wait for the other ranks plus its transfer."""


class Monitor(Protocol):
    """Called after every PPO update with the live policy; returns True to end training there.

    `status` is a short line for the progress bar. The loop does not count the time a call takes as
    training time (train_s excludes it, and SPS windows skip it)."""

    status: str

    def __call__(self, policy: CognitiveMambaPolicy, step_id: int, train_s: float) -> bool: ...


class StageTimers:
    """Time per stage, read as ms per env step once per log line.

    Without `sync` (training's default) a stage's time is the host's wall time between its boundaries; on
    CUDA that is mostly launch time, since kernels run on after the host moves on. With `sync` on CUDA
    (benchmarks) a pair of CUDA events brackets every stage on the current stream and the GPU time
    between them is read at the log line, with one wait for the last event: exact stage times with no
    host wait inside the loop, so that timing them does not slow the run it measures."""

    def __init__(self, sync: bool) -> None:
        self.sync = sync
        self.seconds = dict.fromkeys(TIMED, 0.0)
        self.spans: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []  # recorded, not yet read
        self.pool: list[torch.cuda.Event] = []  # events already read, recorded again (allocated once)

    def _event(self) -> torch.cuda.Event:
        event = self.pool.pop() if self.pool else torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        if self.sync:
            start = self._event()
            yield
            self.spans.append((stage, start, self._event()))
            return
        t0 = time.perf_counter()
        yield
        self.seconds[stage] += time.perf_counter() - t0

    def read(self, steps: int) -> dict[str, float]:
        """ms per env step (all actors) per stage since the last read, then clear."""
        if self.spans:
            self.spans[-1][2].synchronize()
            for stage, start, end in self.spans:
                self.seconds[stage] += start.elapsed_time(end) / 1000.0
                self.pool += (start, end)
            self.spans.clear()
        out = {f"ms_{k}": 1000.0 * v / max(steps, 1) for k, v in self.seconds.items()}
        self.seconds = dict.fromkeys(TIMED, 0.0)
        return out


@dataclass
class TrainState:
    """Counters carried across resumes."""

    step_id: int = 0
    episode_count: int = 0
    reward_ema: float = 0.0
    wall_time_hours: float = 0.0
    skipped_updates: int = 0
    parent_checkpoint: str | None = None


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
    sync: Sync | None = None,
    check_storage: bool = False,
    forward: Forward | None = None,
) -> tuple[tuple[torch.Tensor, torch.Tensor, CoreState], torch.Tensor]:
    """Fill the storage with one rollout; returns the new (obs, resets, state) carry and the mean
    extrinsic reward per actor-step (a device scalar). With `sync` the RND normaliser follows every
    rank's actors (3 numbers all-reduced per step). With `check_storage` (a run's first rollout) the
    stored form of step 1's observation is compared with what the policy saw (one host read). `forward`
    is the rollout's policy step (default: the eager `rollout_forward`; `make_forward` compiles it)."""
    forward = forward or rollout_forward(policy, memory, reduce=None if sync is None else sync.sum_)
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
    advantages over the ranks before the objective (a collective the graph cannot hold)."""
    fn = ppo_objective(policy, cfg, cfg.ppo.norm_adv and not distributed)
    if cfg.compile and cfg.compile_update and device.type == "cuda":
        return cast(Objective, compile_graph(fn, fullgraph=cfg.engine.temporal_core != "gru"))
    return fn


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
    sync: Sync | None = None,
    objective: Objective | None = None,
) -> tuple[dict[str, torch.Tensor], int]:
    """PPO epochs over sequence minibatches. A non-finite loss or gradient norm skips that optimizer
    step and is counted. With a fused optimizer (the learner's on CUDA) the skip happens on the device
    (`found_inf`) and the count is read once per update, so the host never waits for a minibatch;
    otherwise one host read per minibatch decides. Returns mean metrics (device) and the skip count.

    With `sync` (a data-parallel run, equal minibatches on every rank) the advantages are normalised
    over the union of the ranks' minibatches and the gradients averaged over ranks before clipping (one
    all-reduce of a flat buffer that carries the non-finite-loss flags too): a step on W ranks is a
    single-process step on the union, and every rank takes the same skip decision.

    `objective` (make_objective; default the eager one) computes each minibatch's loss and metrics."""
    p = cfg.ppo
    objective = objective or ppo_objective(policy, cfg, p.norm_adv and sync is None)
    params = [q for q in policy.parameters() if q.requires_grad]
    sums: dict[str, torch.Tensor] = {}
    count, skipped = 0, 0
    on_device = bool(optimizer.defaults.get("fused"))  # the optimizer skips a step itself on found_inf
    skips = torch.zeros((), device=params[0].device)  # () float32, steps skipped on the device
    for _ in range(p.ppo_epochs):
        for mb in buf.minibatches(p.num_minibatches, gen):
            adv = mb.advantages  # (L, M)
            if sync is not None and p.norm_adv:
                adv = sync.normalize(mb.advantages)  # (L, M) over all ranks
            total, metrics = objective(
                mb.obs, mb.resets, mb.state, mb.actions, mb.logp, adv, mb.values, mb.returns
            )  # (), {name: ()}
            if p.target_kl > 0:
                kl = metrics["approx_kl"] if sync is None else sync.mean({"kl": metrics["approx_kl"]})["kl"]
                adapt_lr(optimizer, kl, p.target_kl, p.lr_min, p.lr_max)
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            if sync is None:
                grad_norm = torch.nn.utils.clip_grad_norm_(params, p.max_grad_norm)
                ok = torch.isfinite(total) & torch.isfinite(grad_norm)  # () bool
            else:
                some_loss_bad = sync.average_grads(total)  # () bool, the same on every rank
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


def scene_names(env: BatchedEnv) -> list[str]:
    """Names of the scenes an env flies (the drone env's corpus), [] for the toy env."""
    infos = getattr(getattr(env, "corpus", None), "infos", None) or []
    return [str(getattr(info, "name", "")) for info in infos]


class Clock:
    """Training time (wall time less what the monitor took) and the window the SPS of a log line covers."""

    def __init__(self) -> None:
        self.t_start = self.t_window = time.perf_counter()
        self.paused = 0.0  # seconds spent in the monitor, not training
        self.steps_window = 0

    def train_s(self) -> float:
        return time.perf_counter() - self.t_start - self.paused

    def pause(self, seconds: float) -> None:
        """Leave `seconds` out of training time and out of the SPS window."""
        self.paused += seconds
        self.t_window += seconds

    def window_sps(self) -> float:
        """Env steps per second since the last call; starts a new window."""
        now = time.perf_counter()
        sps = self.steps_window / (now - self.t_window)
        self.t_window, self.steps_window = now, 0
        return sps


@dataclass
class Learner:
    """One run's learner: the policy and its optimizer, the rollout buffers, the run folder, the counters."""

    cfg: TrainConfig
    env: BatchedEnv
    dist: Dist
    sync: Sync | None
    run: RunFiles
    policy: CognitiveMambaPolicy
    optimizer: torch.optim.Optimizer
    buf: RolloutStorage
    memory: EpisodicMemory
    stats: EpisodeStats
    timers: StageTimers
    forward: Forward  # the rollout's policy step (make_forward)
    objective: Objective  # the update's minibatch objective (make_objective)
    gen: torch.Generator  # minibatch order
    state: TrainState
    ema: torch.Tensor  # () float32, the extrinsic reward's moving average
    fresh_ema: bool
    corpus_summary: dict[str, Any]
    base_episodes: int = 0  # the resumed run's counters
    base_hours: float = 0.0
    last_checkpoint: Path | None = None  # the newest checkpoint this run wrote

    def track_reward(self, ext_mean: torch.Tensor) -> None:
        """Fold one rollout's mean extrinsic reward into the moving average (its first value on a fresh run)."""
        decay = 0.0 if self.fresh_ema else self.cfg.ppo.reward_ema_decay
        self.ema = decay * self.ema + (1 - decay) * ext_mean
        self.fresh_ema = False

    def sync_counters(self, clock: Clock) -> None:
        """Bring the host counters up to date (host reads; every rank's episodes)."""
        st = self.state
        st.reward_ema = float(self.ema)
        episodes = self.stats.episodes_total
        episodes = episodes if self.sync is None else self.sync.sum_(episodes.clone())  # ()
        st.episode_count = self.base_episodes + int(episodes)
        st.wall_time_hours = self.base_hours + (time.perf_counter() - clock.t_start) / 3600.0

    def checkpoint(self, clock: Clock) -> Path:
        """Save weights, optimizer and counters (rank 0 writes); returns the checkpoint's path.

        A write that fails (a full disk) leaves no file, logs one error line, counts in
        navi_write_errors_total{what="checkpoint"} and returns the last good checkpoint instead (the
        path not written when there is none): training goes on."""
        self.sync_counters(clock)
        st, cfg = self.state, self.cfg
        path = self.run.checkpoints / checkpoint_name(st.step_id)
        if not self.dist.main:
            return path
        meta = CheckpointMeta(
            step_id=st.step_id,
            episode_count=st.episode_count,
            reward_ema=st.reward_ema,
            wall_time_hours=st.wall_time_hours,
            temporal_core=cfg.engine.temporal_core,
            run_id=self.run.run_id,
            config=cfg.to_dict(),
            obs_shape=list(self.env.obs_shape),
            parent_checkpoint=st.parent_checkpoint,
            corpus_summary=self.corpus_summary,
        )
        try:
            save_checkpoint(path, self.policy.state_dict(), self.optimizer.state_dict(), meta)
        except OSError as err:
            count_write_error("checkpoint")
            line = (
                f"checkpoint {path.name} not written: {os_reason(err)}; training goes on, the last "
                f"good checkpoint is {self.last_checkpoint or 'none yet'}"
            )
            self.run.logger.error(line)
            log.error(line)
            return self.last_checkpoint or path
        self.last_checkpoint = path
        prune_checkpoints(self.run.checkpoints, cfg.keep_checkpoints)
        self.run.logger.info(f"checkpoint {path}")
        return path


def resume(
    policy: CognitiveMambaPolicy, optimizer: torch.optim.Optimizer, path: Path, cfg: TrainConfig
) -> TrainState:
    """Load weights and optimizer from a checkpoint of the same temporal core; returns its counters.

    A run folder (or its checkpoints/ folder) resumes from its newest checkpoint that verifies."""
    if path.is_dir():
        found = newest_good_checkpoint(path)
        if found is None:
            raise CheckpointError(f"no checkpoint in {path} loads and verifies")
        path = found
    ckpt = load_checkpoint(path, next(policy.parameters()).device)
    if ckpt.meta.temporal_core != cfg.engine.temporal_core:
        raise ValueError(
            f"{path} uses temporal core {ckpt.meta.temporal_core}, not {cfg.engine.temporal_core}"
        )
    policy.load_state_dict(ckpt.model)
    if ckpt.optimizer is not None:
        optimizer.load_state_dict(ckpt.optimizer)  # its moments, and its rate where that adapts
        if cfg.ppo.target_kl <= 0:  # a constant rate is this run's own, never the checkpoint's
            for group in optimizer.param_groups:
                group["lr"] = cfg.ppo.lr
    m = ckpt.meta
    return TrainState(m.step_id, m.episode_count, m.reward_ema, m.wall_time_hours, 0, str(path))


def setup(
    env: BatchedEnv,
    cfg: TrainConfig,
    *,
    run_dir: Path | None,
    run_id: str | None,
    resume_from: Path | None,
    on_log: Callable[[str, dict[str, float]], None] | None,
    corpus_summary: dict[str, Any] | None,
    dist: Dist,
) -> Learner:
    """Everything before the first rollout: the resolved config, the policy (fresh, or resumed and, on
    several ranks, broadcast so every replica starts equal), the optimizer, the run folder and its
    manifest, and the buffers, allocated once."""
    d = dist
    device = env.device
    compact = compact_storage(cfg, bool(getattr(env, "compact_obs", False)))
    cfg = resolve(
        replace(cfg, n_actors=cfg.n_actors or env.n_actors, device=str(device)), env.obs_shape, compact
    )
    if cfg.n_actors != env.n_actors:
        raise ValueError(f"config asks for {cfg.n_actors} actors but the env has {env.n_actors}")
    torch.manual_seed(cfg.seed)
    rank_seed = cfg.seed + d.rank  # env resets, action sampling and minibatch order differ per rank
    run_id = run_id or new_run_id()
    root = run_dir or Path("artifacts/runs") / run_id
    policy = CognitiveMambaPolicy(env.obs_shape, cfg.engine).to(device)
    policy.amp = cfg.amp and device.type == "cuda"
    params = [q for q in policy.parameters() if q.requires_grad]
    optimizer = torch.optim.Adam(params, lr=cfg.ppo.lr, eps=1e-5, fused=device.type == "cuda")
    timers = StageTimers(cfg.sync_timers and device.type == "cuda")
    sync = Sync(d, params, device, timers) if d.active else None
    if sync is not None:
        run_id, root = sync.broadcast_object((run_id, root))
    run = RunFiles(root, run_id, on_log, write=d.main)
    st = TrainState() if resume_from is None else resume(policy, optimizer, resume_from, cfg)
    for group in optimizer.param_groups:  # adaptive: a device tensor the update adjusts in place
        lr = float(group["lr"])
        group["lr"] = torch.tensor(lr, device=device) if cfg.ppo.target_kl > 0 else lr
    manifest: dict[str, Any] = {
        "config": cfg.to_dict(),
        "obs_shape": list(env.obs_shape),
        "device": str(device),
        "resume_from": st.parent_checkpoint,
        "corpus_summary": corpus_summary or {},
    }
    if sync is not None:
        sync.broadcast_module(policy)  # identical replicas, fresh or resumed
        torch.manual_seed(rank_seed)
        ranks = sync.gather_object(
            {"rank": d.rank, "seed": rank_seed, "device": str(device), "scenes": scene_names(env)}
        )
        manifest.update(world_size=d.world, actors_per_rank=cfg.n_actors, ranks=ranks)
    if cfg.compile and device.type == "cuda":
        policy.encoder.compile(dynamic=False)
    if cfg.tf32 and device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
    run.write_manifest("run", manifest)
    run.logger.info(f"start: {cfg.n_actors} actors, T={cfg.rollout_length}, core={cfg.engine.temporal_core}")
    shaping_gamma = getattr(getattr(getattr(env, "config", None), "reward", None), "shaping_gamma", None)
    if shaping_gamma is not None and abs(shaping_gamma - cfg.ppo.gamma) > 1e-9:
        run.logger.warning(
            f"the env's shaping_gamma {shaping_gamma} differs from PPO's gamma {cfg.ppo.gamma}: "
            "potential-based shaping is then no longer policy-invariant"
        )
    n = cfg.n_actors
    buf = RolloutStorage(
        cfg.rollout_length,
        n,
        env.obs_shape,
        policy.initial_state(n, device),
        cfg.ppo.bptt_chunk,
        device,
        compact,
        bool(getattr(env, "goal_marks", False)),
    )
    memory = EpisodicMemory(
        n, cfg.engine.memory_slots, cfg.engine.embed_dim, cfg.engine.memory_threshold, device
    )
    return Learner(
        cfg=cfg,
        env=env,
        dist=d,
        sync=sync,
        run=run,
        policy=policy,
        optimizer=optimizer,
        buf=buf,
        memory=memory,
        stats=EpisodeStats(n, device),
        timers=timers,
        forward=make_forward(policy, memory, cfg, device, None if sync is None else sync.sum_),
        objective=make_objective(policy, cfg, device, sync is not None),
        gen=torch.Generator().manual_seed(rank_seed),
        state=st,
        ema=torch.full((), st.reward_ema, device=device),  # () float32
        fresh_ema=resume_from is None,
        corpus_summary=corpus_summary or {},
        base_episodes=st.episode_count,
        base_hours=st.wall_time_hours,
    )


def first_carry(lrn: Learner) -> tuple[torch.Tensor, torch.Tensor, CoreState]:
    """Reset every actor: the first (obs, resets, recurrent state) a rollout starts from."""
    n, device = lrn.cfg.n_actors, lrn.env.device
    obs = lrn.env.reset(seed=lrn.cfg.seed + lrn.dist.rank)  # (N, 3, Az, El)
    starts = torch.ones(n, dtype=torch.bool, device=device)  # (N,) every actor starts an episode
    return obs, starts, lrn.policy.initial_state(n, device)


def log_row(
    lrn: Learner, clock: Clock, metrics: dict[str, torch.Tensor], bar: Progress, status: str
) -> dict[str, float]:
    """One log line: counters, SPS, the update's metrics (averaged over ranks), episode statistics and
    ms per stage; written to the run's metrics and shown on the progress bar."""
    steps_window = clock.steps_window
    sps = clock.window_sps()
    lrn.sync_counters(clock)
    st, sync, d = lrn.state, lrn.sync, lrn.dist
    metrics = metrics if sync is None else sync.mean(metrics)  # averaged over ranks
    row = {
        "step": float(st.step_id),
        "train_s": clock.train_s(),
        "sps": sps,
        "reward_ema": st.reward_ema,
        "episode_count": float(st.episode_count),
        "skipped_updates": float(st.skipped_updates),
        **{k: float(v) for k, v in metrics.items()},
        **lrn.stats.read(None if sync is None else sync.sum_),
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
        try:
            entry = registry.maybe_promote(
                latest, notes=f"auto-promote of run {run.run_id}", tags=("rl", cfg.engine.temporal_core)
            )
            promoted = entry.version if entry is not None else None
        except OSError as err:  # the registry keeps its last good state (ModelRegistry.promote)
            count_write_error("registry")
            line = f"model registry {registry.root}: {latest.name} not promoted: {os_reason(err)}"
            run.logger.error(line)
            log.error(line)
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
    if sync is not None:
        summary["ranks"] = d.world
    report = write_report(run, summary)
    run.logger.info(f"done: {summary}")
    write_debug(d, lrn.policy, lrn.optimizer, st.step_id)
    if sync is not None:
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
            if sync is not None:
                interrupted, stopped, ext_mean = sync.agree(interrupted, stopped, ext_mean)
            lrn.track_reward(ext_mean)
            # log
            if updates % cfg.log_every == 0 or st.step_id >= cfg.total_steps or stopped:
                row = log_row(lrn, clock, metrics, bar, monitor.status if monitor is not None else "")
            # checkpoint
            if st.step_id >= next_ckpt and st.step_id < cfg.total_steps and not (stopped or interrupted):
                lrn.checkpoint(clock)
                next_ckpt += cfg.checkpoint_every
    except KeyboardInterrupt:
        if sync is not None:
            raise  # mid-collective: this rank cannot checkpoint with the others (signals set a flag instead)
        interrupted = True
        lrn.run.logger.warning("interrupted: saving a checkpoint")
    bar.close()
    return finish(lrn, clock, start_step, registry, interrupted, stopped, row)
