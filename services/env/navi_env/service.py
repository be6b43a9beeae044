"""`navi serve env`: the drone environment over Zenoh, so an external brain can fly the drones.

A queryable at `navi/env/step` takes a StepRequest (actions for some or all actors, or a reset) and
answers a StepResult with the rewards, episode flags and the requested actors' next observation.
Actors not named in a request hover (zero action) for that step. Actor 0's observation is also
published on `navi/env/observations` (best-effort, at most `observation_hz`) for dashboards.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from navi_contracts.models import DistanceMatrix, StepRequest, StepResult
from navi_contracts.topics import OBSERVATIONS, STEP
from navi_env.config import EnvConfig
from navi_env.sim.env import SdfDagEnv
from navi_mesh import metrics
from navi_mesh.liveliness import declare_alive
from navi_mesh.messages import distance_matrix
from navi_mesh.pubsub import QueuedPublisher, RequestQueue
from navi_mesh.session import SessionConfig, session

log = logging.getLogger("navi_env.service")

SERVICE = "env"


@dataclass(frozen=True)
class EnvServiceConfig:
    """One `navi serve env` process."""

    corpus: Path = Path("artifacts/corpus/default")
    """Corpus folder (manifest.json + .gmdag scenes)."""
    actors: int = 4
    """N actors the external brain flies."""
    device: str = "cpu"
    """Torch device of the environment."""
    seed: int = 0
    """Environment seed."""
    observation_hz: float = 10.0
    """Upper bound on the rate of actor 0's published observation."""
    metrics_port: int = 9100
    """Port of GET /metrics (Prometheus)."""
    metrics_host: str = "127.0.0.1"
    """Interface of the metrics endpoint."""
    env: EnvConfig = field(default_factory=EnvConfig)
    """Observation, physics and reward settings."""
    session: SessionConfig = field(default_factory=SessionConfig)
    """How to reach the Zenoh router."""


class StepError(ValueError):
    """A StepRequest that does not fit this environment."""


def load_env(cfg: EnvServiceConfig) -> SdfDagEnv:
    """The environment of a corpus folder, with the manifest's qualified spawns."""
    from navi_env.corpus.folder import load_corpus_folder

    scenes, manifest = load_corpus_folder(cfg.corpus, torch.device(cfg.device))
    return SdfDagEnv(scenes, cfg.actors, cfg.device, cfg.env, spawns=manifest.spawn_tensors(), seed=cfg.seed)


def _check_ids(env_ids: np.ndarray, n: int) -> torch.Tensor:
    if env_ids.size == 0:
        raise StepError("a StepRequest must name at least one actor")
    if int(env_ids.min()) < 0 or int(env_ids.max()) >= n:
        raise StepError(f"env_ids must be in [0, {n}), got [{int(env_ids.min())}, {int(env_ids.max())}]")
    if np.unique(env_ids).size != env_ids.size:
        raise StepError("env_ids must not repeat")
    return torch.from_numpy(env_ids.astype(np.int64))  # (K,) int64


def apply_step(env: SdfDagEnv, req: StepRequest, step_id: int) -> tuple[StepResult, int]:
    """Run one request on the env; returns the StepResult and the new step counter."""
    ids = _check_ids(req.env_ids, env.n_actors).to(env.device)  # (K,)
    if not np.isfinite(req.actions).all():
        raise StepError("actions must be finite")
    k = ids.shape[0]
    if req.reset:
        obs = env.reset()  # (N, 3, Az, El)
        reward = torch.zeros(k)  # (K,)
        done = truncated = torch.zeros(k, dtype=torch.bool)  # (K,)
        ret = torch.zeros(k)  # (K,)
        step_id = 0
    else:
        actions = torch.zeros(env.n_actors, 4, device=env.device)  # (N, 4) others hover
        actions[ids] = torch.from_numpy(np.array(req.actions, dtype=np.float32)).to(env.device)
        out = env.step(actions)
        obs = out.obs  # (N, 3, Az, El)
        reward, done, truncated = out.reward[ids].cpu(), out.done[ids].cpu(), out.truncated[ids].cpu()  # (K,)
        ret = out.info["episode_return"][ids].cpu()  # (K,)
        step_id += 1
        metrics.STEPS.labels("env").inc(env.n_actors)
        metrics.EPISODES.labels("env").inc(int((out.done | out.truncated).sum()))
    result = StepResult(
        request_id=req.request_id,
        step_id=step_id,
        env_ids=np.ascontiguousarray(req.env_ids, dtype=np.int32),  # (K,)
        reward=reward.numpy().astype(np.float32),  # (K,)
        done=done.numpy().astype(bool),  # (K,)
        truncated=truncated.numpy().astype(bool),  # (K,)
        episode_return=ret.numpy().astype(np.float32),  # (K,)
        observation=distance_matrix(obs[ids].cpu().numpy(), req.env_ids, step_id),
    )
    return result, step_id


def serve_env(cfg: EnvServiceConfig, stop: threading.Event) -> None:
    """Answer StepRequests until `stop` is set."""
    metrics.serve_metrics(cfg.metrics_port, "env", cfg.metrics_host)
    env = load_env(cfg)
    obs = env.reset(seed=cfg.seed)  # (N, 3, Az, El)
    sess = session(cfg.session)
    token = declare_alive(sess, SERVICE)
    steps: RequestQueue[StepRequest] = RequestQueue(sess, STEP)
    observations: QueuedPublisher[DistanceMatrix] = QueuedPublisher(sess, OBSERVATIONS, capacity=4)
    period = 1.0 / cfg.observation_hz
    last_pub = 0.0
    step_id = 0
    log.info("env service ready: %d actors on %s, corpus %s", cfg.actors, cfg.device, cfg.corpus)
    try:
        while not stop.is_set():
            item = steps.get(0.2)
            if item is None:
                continue
            try:
                result, step_id = apply_step(env, item.message, step_id)
            except StepError as err:
                metrics.STEP_REQUESTS.labels("error").inc()
                item.fail(f"StepError: {err}")
                continue
            item.reply(result)
            metrics.STEP_REQUESTS.labels("ok").inc()
            if item.received_at - last_pub >= period:
                last_pub = item.received_at
                observations.publish(distance_matrix(obs[:1].cpu().numpy(), np.zeros(1, np.int32), step_id))
    finally:
        observations.close()
        steps.close()
        token.undeclare()
