"""`serve_learner`, the service itself: the control plane and the liveliness token, then the corpus, then
the environment wrapped in the tap, the floor planner and the run (training or inference), and the
teardown."""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import torch

from navi_learner.config import default_actors
from navi_learner.envs.factory import make_env
from navi_learner.ppo.dist import Dist
from navi_learner.service import FrameRepeater, TelemetryTap
from navi_learner.service.bring_up import CorpusReporter, Heartbeat, ServiceStatus, prepare_corpus
from navi_learner.service.config import SERVICE, LearnerServiceConfig
from navi_learner.service.floor_plan import FloorPlanner
from navi_learner.service.loops import run_inference, run_training, train_rank
from navi_learner.service.publishers import MeshPublishers
from navi_learner.serving.control_plane import ControlPlaneConfig, create_app
from navi_learner.serving.registry import ModelRegistry
from navi_mesh.liveliness import declare_alive
from navi_mesh.session import session

log = logging.getLogger(__name__)


def control_plane_config(cfg: LearnerServiceConfig) -> ControlPlaneConfig:
    return ControlPlaneConfig(cfg.models_dir, cfg.api_token, SERVICE, cfg.api_read_only)


def start_control_plane(
    cfg: LearnerServiceConfig, pubs: MeshPublishers, status: ServiceStatus
) -> tuple[Any, threading.Thread] | None:
    """uvicorn serving the control plane from a daemon thread (None when api_port is 0)."""
    if cfg.api_port == 0:
        return None
    import uvicorn

    if cfg.api_read_only:
        log.warning("the control plane is read-only (--read-only): every mutation answers 503")
    app = create_app(control_plane_config(cfg), pubs.promotions.publish, status)
    server = uvicorn.Server(uvicorn.Config(app, host=cfg.api_host, port=cfg.api_port, log_level="warning"))
    thread = threading.Thread(target=server.run, name="control plane", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30.0
    while not server.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    if not server.started:
        raise OSError(f"the control plane did not start on {cfg.api_host}:{cfg.api_port} (port in use?)")
    return server, thread


def serve_learner(
    cfg: LearnerServiceConfig, stop: threading.Event, dist: Dist | None = None
) -> dict[str, Any]:
    """Run the learner service; returns the run summary (also written to the log as JSON).

    Order: control plane and liveliness token (the service answers /healthz within seconds), then the
    corpus (built over compile jobs when missing), then the environment and the run. On a data-parallel
    learner (`dist`, several ranks) this is rank 0; the other ranks run `train_rank`."""
    d = dist or Dist()
    if not d.main:
        return train_rank(cfg, stop, d)
    if d.active and cfg.mode != "train":
        raise ValueError("only training runs on several ranks (--nproc); inference is one process")
    if cfg.api_port != 0:
        control_plane_config(cfg).check()  # fail fast: mutations enabled without a token
    for action in ModelRegistry(cfg.models_dir).recover():  # after a writer was killed mid-write
        log.warning("model registry %s: %s", cfg.models_dir, action)
    device = torch.device(cfg.train.device)
    n = cfg.train.n_actors or default_actors(device)
    sess = session(cfg.session)
    pubs = MeshPublishers(sess, cfg.telemetry_capacity)
    status = ServiceStatus(cfg.corpus if cfg.env_kind == "sdfdag" else None)
    reporter = CorpusReporter(status, pubs)
    plane = start_control_plane(cfg, pubs, status)
    token = declare_alive(sess, SERVICE)  # after the control plane listens: the token means reachable
    heartbeat = Heartbeat(status, pubs, reporter)
    repeater: FrameRepeater | None = None
    planner: FloorPlanner | None = None
    try:
        try:
            prepare_corpus(cfg, sess, reporter, stop)
        except InterruptedError:
            return {"steps": 0, "interrupted": True}
        if stop.is_set():
            return {"steps": 0, "interrupted": True}
        base_env = make_env(
            cfg.corpus if cfg.env_kind == "sdfdag" else None,
            n,
            cfg.train.device,
            cfg.train.seed,
            cfg.env_kind,
            rank=d.rank,
            world=d.world,
            rank_scenes=cfg.train.rank_scenes,
        )
        tap = TelemetryTap(base_env, pubs, cfg.observation_hz)
        heartbeat.tap = tap
        repeater = FrameRepeater(tap, pubs)
        scenes = getattr(base_env, "corpus", None)
        if scenes is not None:
            planner = FloorPlanner(scenes, pubs, lambda: tap.run_id)
            tap.on_pose = planner.request
        if stop.is_set():  # a signal while the environment was built: no run starts
            return {"steps": 0, "interrupted": True}
        if cfg.mode == "train":
            summary = run_training(cfg, tap, pubs, status, d, stop)
        else:
            summary = run_inference(cfg, tap, pubs, sess, stop, status)
        status.update(phase="done")
        repeater.close()  # the run is over: no frame is repeated as if it were live
        log.info("run finished: %s", json.dumps(summary, default=str))
        if not cfg.exit_when_done:
            stop.wait()  # a signal sets it
            log.info("stopping")
    except BaseException:
        status.update(phase="failed")
        raise
    finally:
        heartbeat.close()
        if planner is not None:
            planner.close()
        if repeater is not None:
            repeater.close()
        if plane is not None:
            server, thread = plane
            server.should_exit = True
            thread.join(timeout=5.0)
        pubs.close()
        token.undeclare()
    return summary
