"""One run's learner and how a run gets it: the policy and its optimizer, the rollout buffers, the run
folder and the counters (Learner), set up fresh or resumed from a checkpoint before the first rollout
(setup), and the checkpoints it writes."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import torch

from navi_learner.config import EngineConfig, TemporalCoreName, TrainConfig, compact_storage, resolve
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.engine.temporal import CoreState
from navi_learner.envs.protocol import BatchedEnv, capabilities
from navi_learner.ppo.compile import Forward, Objective, make_forward, make_objective
from navi_learner.ppo.dist import Collectives, Dist, collectives
from navi_learner.ppo.rollout import RolloutStorage
from navi_learner.ppo.runs import RunFiles, new_run_id
from navi_learner.ppo.stats import EpisodeStats
from navi_learner.ppo.timing import Clock, StageTimers
from navi_learner.serving.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    checkpoint_name,
    count_write_error,
    load_checkpoint,
    newest_good_checkpoint,
    os_reason,
    prune_checkpoints,
    read_meta,
    save_checkpoint,
)
from navi_learner.serving.references import checkpoint_path

log = logging.getLogger(__name__)


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
class Learner:
    """One run's learner: the policy and its optimizer, the rollout buffers, the run folder, the counters."""

    cfg: TrainConfig
    env: BatchedEnv
    dist: Dist
    sync: Collectives  # Sync on several ranks, Solo on one
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
        episodes = self.sync.sum_(episodes.clone())  # () over every rank
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


class InitError(ValueError):
    """TrainConfig.init_from names no checkpoint, or one whose weights do not fit the run's engine."""


def init_engine(spec: str, temporal_core: TemporalCoreName, overrides: Mapping[str, Any]) -> EngineConfig:
    """The engine of a fresh run that starts from `spec`'s weights (TrainConfig.init_from): the one the
    checkpoint stored (its shape and view range), with the run's temporal core and `overrides` (the run's
    own EngineConfig fields, a CLI's --engine) on top, so a checkpoint of another shape than today's
    default engine starts a run of its own shape. InitError when `spec` is not a checkpoint; a temporal
    core or override that does not fit its weights fails later, in init_weights."""
    path = checkpoint_path(spec)
    try:
        meta = read_meta(path)
    except CheckpointError as err:
        raise InitError(f"init_from: {err}") from err
    return replace(EngineConfig.from_dict(meta.config["engine"]), temporal_core=temporal_core, **overrides)


def engine_differences(stored: EngineConfig, run: EngineConfig) -> str:
    """The fields where a checkpoint's engine and a run's differ, as `name=stored (the run's value)`."""
    names = [f.name for f in fields(EngineConfig) if getattr(stored, f.name) != getattr(run, f.name)]
    return ", ".join(f"{n}={getattr(stored, n)!r} (the run's {getattr(run, n)!r})" for n in names)


def init_weights(policy: CognitiveMambaPolicy, spec: str, cfg: TrainConfig) -> Path:
    """Load a checkpoint's weights and novelty statistics (the policy's state) into a fresh run's
    policy; `spec` a path, or a task's name for its shipped reference (references.checkpoint_path).
    Nothing else is taken: the optimizer, counters and reward average stay fresh. Returns the path;
    InitError when it is not a checkpoint or does not fit the engine."""
    path = checkpoint_path(spec)
    try:
        ckpt = load_checkpoint(path, next(policy.parameters()).device)
    except CheckpointError as err:
        raise InitError(f"init_from: {err}") from err
    if ckpt.meta.temporal_core != cfg.engine.temporal_core:
        raise InitError(
            f"init_from {path} uses temporal core {ckpt.meta.temporal_core}, not {cfg.engine.temporal_core}"
        )
    try:
        policy.load_state_dict(ckpt.model)
    except RuntimeError as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        differ = engine_differences(EngineConfig.from_dict(ckpt.meta.config["engine"]), cfg.engine)
        raise InitError(
            f"init_from {path}: its weights do not fit this run's engine ({first}); "
            f"the checkpoint's engine has {differ or 'the same fields'}"
        ) from err
    return path


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
    caps = capabilities(env)
    compact = compact_storage(cfg, caps.compact_obs)
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
    sync = collectives(d, params, device, timers)
    run_id, root = sync.broadcast_object((run_id, root))
    run = RunFiles(root, run_id, on_log, write=d.main)
    st = TrainState() if resume_from is None else resume(policy, optimizer, resume_from, cfg)
    init = init_weights(policy, cfg.init_from, cfg) if resume_from is None and cfg.init_from else None
    for group in optimizer.param_groups:  # adaptive: a device tensor the update adjusts in place
        lr = float(group["lr"])
        group["lr"] = torch.tensor(lr, device=device) if cfg.ppo.target_kl > 0 else lr
    manifest: dict[str, Any] = {
        "config": cfg.to_dict(),
        "obs_shape": list(env.obs_shape),
        "device": str(device),
        "resume_from": st.parent_checkpoint,
        "init_from": str(init) if init is not None else None,
        "corpus_summary": corpus_summary or {},
    }
    sync.broadcast_module(policy)  # identical replicas, fresh or resumed
    if d.active:
        torch.manual_seed(rank_seed)
        ranks = sync.gather_object(
            {"rank": d.rank, "seed": rank_seed, "device": str(device), "scenes": list(caps.scenes)}
        )
        manifest.update(world_size=d.world, actors_per_rank=cfg.n_actors, ranks=ranks)
    if cfg.compile and device.type == "cuda":
        policy.encoder.compile(dynamic=False)
    if cfg.tf32 and device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
    run.write_manifest("run", manifest)
    run.logger.info(f"start: {cfg.n_actors} actors, T={cfg.rollout_length}, core={cfg.engine.temporal_core}")
    shaping_gamma = caps.shaping_gamma
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
        caps.goal_marks,
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
        forward=make_forward(policy, memory, cfg, device, sync),
        objective=make_objective(policy, cfg, device, sync.pools_advantages),
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
