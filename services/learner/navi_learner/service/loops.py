"""The loops the service runs: training (`train` with the tap and the metrics callback; a rank other
than 0 of a data-parallel learner trains without the mesh) and inference (a model flown until stopped,
reloaded when its followed alias moves)."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import torch
import zenoh

from navi_contracts.models import (
    ModelPromoted,
)
from navi_contracts.topics import MODEL_PROMOTED
from navi_learner.config import default_actors
from navi_learner.envs.factory import corpus_summary, make_env
from navi_learner.ppo.dist import Dist
from navi_learner.service import TelemetryTap, TrainingMetrics
from navi_learner.service.bring_up import ServiceStatus
from navi_learner.service.config import LearnerServiceConfig
from navi_learner.service.publishers import MeshPublishers, telemetry_rows
from navi_learner.serving.checkpoint import RUN_CHECKPOINTS, newest_good_checkpoint, read_meta
from navi_learner.serving.registry import ModelRegistry, RegistryError
from navi_mesh import metrics
from navi_mesh.messages import telemetry
from navi_mesh.pubsub import subscribe

log = logging.getLogger(__name__)


def run_training(
    cfg: LearnerServiceConfig,
    env: TelemetryTap,
    pubs: MeshPublishers,
    status: ServiceStatus,
    dist: Dist | None = None,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    """`train` with the tap and the metrics callback; returns the run summary. A set `stop` (a signal)
    ends training after the update in progress, with a checkpoint; rank 0 of a data-parallel learner
    also passes its Dist, and the ranks agree on stopping."""
    from navi_learner.ppo.runs import new_run_id
    from navi_learner.ppo.train import train

    d = dist or Dist()
    run_id = new_run_id()
    env.run_id = run_id
    resume_from = cfg.resume_from
    if resume_from is None and cfg.resume_latest:
        resume_from = newest_good_checkpoint(cfg.runs_dir, RUN_CHECKPOINTS)
        log.info("resuming from %s", resume_from or "scratch: no checkpoint under the runs folder loads")
    start_step = read_meta(resume_from).step_id if resume_from is not None else 0
    status.update(
        phase="training", run_id=run_id, actors=env.n_actors * d.world, step=start_step, start_step=start_step
    )
    on_log = TrainingMetrics(pubs, env, env.device, status, d.world)
    result = train(
        env,
        cfg.train,
        run_dir=cfg.runs_dir / run_id,
        run_id=run_id,
        resume_from=resume_from,
        on_log=on_log,
        registry=ModelRegistry(cfg.models_dir),
        corpus_summary=corpus_summary(cfg.corpus if cfg.env_kind == "sdfdag" else None, cfg.env_kind),
        progress=False,
        dist=d if d.active else None,
        should_stop=None if stop is None else stop.is_set,
    )
    summary = {
        "run_id": result.run_id,
        "steps": result.step_id,
        "checkpoint": str(result.final_checkpoint),
        "sps": result.sps,
        "reward_ema": result.reward_ema,
        "interrupted": result.interrupted,
        "promoted": result.promoted,
    }
    pubs.telemetry.publish(telemetry("actor.training.done", 1.0, result.step_id, result.run_id))
    return summary


def resolve_model(model: str, registry: ModelRegistry) -> Path:
    """A checkpoint path, or the file of a registry version or alias."""
    path = Path(model)
    if path.is_file():
        return path
    try:
        return registry.path(model)
    except RegistryError as err:
        raise FileNotFoundError(
            f"{model!r} is neither a checkpoint file nor a registry version: {err}"
        ) from err


def run_inference(
    cfg: LearnerServiceConfig,
    env: TelemetryTap,
    pubs: MeshPublishers,
    sess: zenoh.Session,
    stop: threading.Event,
    status: ServiceStatus,
) -> dict[str, Any]:
    """Fly the model until stopped (or infer_steps), reloading it when the followed alias moves. The
    phase turns to "inference" once the promotion subscriber is declared and the model is loaded, so a
    client that waits for it in /healthz knows its promotions are heard."""
    from navi_learner.evaluation.evaluate import CheckpointPolicy

    registry = ModelRegistry(cfg.models_dir)
    device = env.device
    promoted: list[ModelPromoted] = []

    def on_promoted(msg: ModelPromoted) -> None:
        if msg.alias == cfg.follow_alias:
            promoted.append(msg)

    sub = subscribe(sess, MODEL_PROMOTED, on_promoted) if cfg.follow_alias else None
    path = resolve_model(cfg.model, registry)
    policy = CheckpointPolicy(path, device, cfg.action_noise)
    policy.reset(env.n_actors, device)
    obs = env.reset(cfg.train.seed)  # (N, 3, Az, El)
    resets = torch.ones(env.n_actors, dtype=torch.bool, device=device)  # (N,)
    reward_sum = torch.zeros((), device=device)  # () float32
    status.update(phase="inference", actors=env.n_actors)
    steps = 0
    window_t, window_steps = time.monotonic(), 0
    try:
        while not stop.is_set() and (cfg.infer_steps == 0 or steps < cfg.infer_steps):
            if promoted:
                msg = promoted.pop()
                promoted.clear()
                path = Path(msg.checkpoint)
                policy = CheckpointPolicy(path, device, cfg.action_noise)
                policy.reset(env.n_actors, device)
                resets = torch.ones(env.n_actors, dtype=torch.bool, device=device)  # (N,)
                log.info("loaded %s (%s -> %s)", path, msg.alias, msg.version)
                pubs.telemetry.publish(telemetry("actor.inference.model_reloaded", 1.0, steps))
            actions = policy.act(obs, resets)  # (N, 4)
            out = env.step(actions)
            obs, resets = out.obs, out.done | out.truncated  # (N, 3, Az, El), (N,)
            reward_sum += out.reward.sum()
            steps += 1
            window_steps += 1
            now = time.monotonic()
            if now - window_t >= 1.0:
                actor_steps = window_steps * env.n_actors
                sps = actor_steps / (now - window_t)
                metrics.STEPS.labels("infer").inc(actor_steps)
                metrics.STEPS_PER_SECOND.labels("infer").set(sps)
                metrics.record_gpu_memory(device)
                row = {
                    "step": float(steps * env.n_actors),
                    "sps": sps,
                    "reward_mean": float(reward_sum) / actor_steps,
                }
                for event in telemetry_rows("actor.inference", row, ""):
                    pubs.telemetry.publish(event)
                reward_sum.zero_()
                window_t, window_steps = now, 0
    finally:
        if sub is not None:
            sub.undeclare()
    return {"steps": steps * env.n_actors, "model": str(path)}


def train_rank(cfg: LearnerServiceConfig, stop: threading.Event, d: Dist) -> dict[str, Any]:
    """A rank other than 0 of a data-parallel learner: no control plane, mesh or telemetry. Waits for the
    corpus (rank 0 builds it when missing), then trains its own actors on its share of the scenes."""
    from navi_learner.ppo.train import train

    if cfg.mode != "train":
        raise ValueError("only training runs on several ranks (--nproc); inference is one process")
    if cfg.env_kind == "sdfdag":
        from navi_env.corpus.folder import MANIFEST

        while not (cfg.corpus / MANIFEST).is_file():
            if stop.wait(1.0):
                return {"steps": 0, "interrupted": True}
    n = cfg.train.n_actors or default_actors(torch.device(cfg.train.device))
    corpus = cfg.corpus if cfg.env_kind == "sdfdag" else None
    env = make_env(
        corpus,
        n,
        cfg.train.device,
        cfg.train.seed + d.rank,
        cfg.env_kind,
        rank=d.rank,
        world=d.world,
        rank_scenes=cfg.train.rank_scenes,
    )
    result = train(  # rank 0's run id and folder are broadcast; this rank writes nothing
        env, cfg.train, resume_from=cfg.resume_from, progress=False, dist=d, should_stop=stop.is_set
    )
    return {
        "rank": d.rank,
        "run_id": result.run_id,
        "steps": result.step_id,
        "interrupted": result.interrupted,
    }
