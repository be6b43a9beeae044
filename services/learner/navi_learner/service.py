"""`navi serve learner`: training or inference in-process, on the mesh, with the control plane.

The loop is the learner's own (`train.train` or the inference loop below); this module only taps it:
- `TelemetryTap` wraps the environment the loop steps. At most `observation_hz` times a second it
  copies actor 0's observation and every actor's action to the host and queues them for publishing
  (navi/env/observations, navi/actor/actions). Between samples a step costs one clock read.
- Every log row of `train` becomes TelemetryEvents `actor.training.<name>` and Prometheus gauges;
  inference publishes `actor.inference.<name>` once a second.
- Publishers are drop-oldest queues drained by their own threads: the loop never waits on Zenoh, and
  a router restart costs no step (the session reconnects by itself).
- The FastAPI control plane runs in a uvicorn thread; its promotions are announced on
  navi/models/promoted, and inference reloads the model when its followed alias moves.
- Bring-up: the control plane and the liveliness token come first (seconds after the start), then the
  corpus: when the sdfdag corpus folder has no manifest, the procedural default corpus is built over
  compile jobs on the compiler workers (navi_env.corpus.jobs; `corpus_build="local"` compiles in
  this process instead). Its progress is in /healthz (`phase`, `corpus`), in the navi_corpus_* gauges
  and in `corpus.*` telemetry; training starts when it is ready.
- A heartbeat publishes `actor.training.actors` (or `actor.inference.actors`) once a second while the
  loop runs, so a dashboard knows the mode and the actor count between slow PPO updates.
- With each sampled observation the tap also queues actor 0's pose (navi/actor/pose, from the env's
  `info["position"]` and its yaw); `FloorPlanner` publishes the floor plan of actor 0's scene
  (navi/env/floor_plan: clearance on a horizontal slice at the drone's height, 128 cells on the long
  side) when the scene changes and every 5 s, computed on its own thread.
SIGTERM or Ctrl+C ends training through its KeyboardInterrupt path (a checkpoint is saved first).

Several GPUs (`navi serve learner --nproc N`, run through torchrun; navi_learner/ppo/dist.py): rank 0 is
the service above (control plane, mesh, telemetry, corpus build) and trains its share; every other
rank waits for the corpus, trains its own actors on its own GPU and publishes nothing. A signal sets
the stop event, which ends training after the update in progress on every rank (one checkpoint).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import zenoh

from navi_contracts import telemetry_keys as keys
from navi_contracts.models import (
    Action,
    DistanceMatrix,
    FloorPlan,
    ModelPromoted,
    RobotPose,
    TelemetryEvent,
)
from navi_contracts.topics import ACTIONS, FLOOR_PLAN, MODEL_PROMOTED, OBSERVATIONS, POSES, TELEMETRY
from navi_env.corpus.jobs import BuildProgress, CorpusBuildConfig, build_corpus_over_jobs
from navi_learner.config import TrainConfig, default_actors
from navi_learner.envs.factory import EnvKind, corpus_summary, make_env
from navi_learner.envs.protocol import BatchedEnv, StepLike
from navi_learner.ppo.dist import Dist
from navi_learner.serving.checkpoint import RUN_CHECKPOINTS, newest_good_checkpoint, read_meta
from navi_learner.serving.control_plane import ControlPlaneConfig, create_app
from navi_learner.serving.registry import ModelRegistry, RegistryError
from navi_mesh import metrics
from navi_mesh.liveliness import declare_alive
from navi_mesh.messages import action_message, distance_matrix, telemetry
from navi_mesh.pubsub import Publisher, QueuedPublisher, subscribe
from navi_mesh.session import SessionConfig, session

log = logging.getLogger("navi_learner.service")

SERVICE = "learner"
Mode = Literal["train", "infer"]


@dataclass(frozen=True)
class LearnerServiceConfig:
    """One `navi serve learner` process."""

    mode: Mode = "train"
    """train (PPO) or infer (run a model, follow promotions)."""
    corpus: Path = Path("artifacts/corpus/default")
    """Corpus folder; the procedural default corpus is built there when it has no manifest."""
    corpus_build: Literal["jobs", "local"] = "jobs"
    """How a missing default corpus is built: compile jobs on the compiler workers, or in this process."""
    corpus_scenes: int = 16
    """Procedural scenes of a default corpus built here."""
    corpus_resolution: int = 512
    """Compile resolution of a default corpus built here."""
    env_kind: EnvKind = "sdfdag"
    """sdfdag (the drone env) or toy (tests)."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """The training run (actors, budget, device, seed, engine, PPO)."""
    resume_from: Path | None = None
    """train: checkpoint to resume from."""
    resume_latest: bool = False
    """train: without resume_from, resume from the newest checkpoint under runs_dir that loads (a
    restarted service goes on where it stopped, losing at most the steps since that checkpoint)."""
    model: str = "latest"
    """infer: a checkpoint path, or a registry version or alias."""
    follow_alias: str = "champion"
    """infer: reload the model when this alias is promoted (empty: never)."""
    deterministic: bool = True
    """infer: act with the policy mean."""
    infer_steps: int = 0
    """infer: batched steps to run (0: until stopped)."""
    models_dir: Path = Path("artifacts/models")
    """The model registry."""
    runs_dir: Path = Path("artifacts/runs")
    """Run folders."""
    observation_hz: float = 10.0
    """Rate of actor 0's observation and of the actions on the mesh (5-10 Hz for dashboards)."""
    telemetry_capacity: int = 1024
    """Telemetry queue length (drop-oldest beyond it)."""
    api_host: str = "127.0.0.1"
    """Control plane interface."""
    api_port: int = 8000
    """Control plane port (0: no control plane)."""
    api_token: str = ""
    """Bearer token for mutations (required unless api_read_only)."""
    api_read_only: bool = False
    """Serve the registry read-only (mutations answer 503); the only way to run without a token."""
    exit_when_done: bool = False
    """Exit after the run instead of keeping the control plane up until stopped."""
    session: SessionConfig = field(default_factory=SessionConfig)
    """How to reach the Zenoh router."""


class MeshPublishers:
    """The learner's publishers over one session."""

    def __init__(self, sess: zenoh.Session, telemetry_capacity: int) -> None:
        self.telemetry: QueuedPublisher[TelemetryEvent] = QueuedPublisher(sess, TELEMETRY, telemetry_capacity)
        self.observations: QueuedPublisher[DistanceMatrix] = QueuedPublisher(sess, OBSERVATIONS, capacity=2)
        self.actions: QueuedPublisher[Action] = QueuedPublisher(sess, ACTIONS, capacity=2)
        self.poses: QueuedPublisher[RobotPose] = QueuedPublisher(sess, POSES, capacity=2)
        self.floor_plans: QueuedPublisher[FloorPlan] = QueuedPublisher(sess, FLOOR_PLAN, capacity=1)
        self.promotions: Publisher[ModelPromoted] = Publisher(sess, MODEL_PROMOTED)

    def close(self) -> None:
        for pub in (self.telemetry, self.observations, self.actions, self.poses, self.floor_plans):
            pub.close()
        self.promotions.close()


class TelemetryTap:
    """A BatchedEnv that forwards to `env` and samples observations and actions for the mesh.

    When a sample is due, actor 0's observation and the actions are copied into pinned host buffers
    with non_blocking copies and a CUDA event is recorded; a later step publishes them once the event
    has completed (`event.query()`, no synchronisation). On the CPU the copy is immediate.
    """

    def __init__(self, env: BatchedEnv, pubs: MeshPublishers, hz: float, run_id: str = "") -> None:
        self.env = env
        self.pubs = pubs
        self.period = 1.0 / hz
        self.run_id = run_id
        self.steps = 0  # batched steps
        self.publish_s = 0.0  # time the loop spent in the tap's sampling and publishing
        self._next = 0.0
        cuda = env.device.type == "cuda"
        c, az, el = env.obs_shape
        self._obs_host = torch.zeros(1, c, az, el, pin_memory=cuda)  # (1, 3, Az, El) float32
        self._act_host = torch.zeros(env.n_actors, 4, pin_memory=cuda)  # (N, 4) float32
        self._pose_host = torch.zeros(5, pin_memory=cuda)  # (5,) float32 actor 0: x, y, z, yaw, scene id
        self._has_pose = False  # the env reported a position with the sampled step
        self.on_pose: Callable[[int, float], None] | None = None  # (scene id, z) of each published pose
        self._event: torch.cuda.Event | None = torch.cuda.Event() if cuda else None
        self._pending_step: int | None = None
        self.last_observation: DistanceMatrix | None = None  # the last frame queued (read by FrameRepeater)
        self.last_publish = 0.0  # time.monotonic() of that

    @property
    def n_actors(self) -> int:
        return self.env.n_actors

    @property
    def device(self) -> torch.device:
        return self.env.device

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        return self.env.obs_shape

    def reset(self, seed: int | None = None) -> torch.Tensor:
        return self.env.reset(seed)

    def step(self, actions: torch.Tensor) -> StepLike:
        out = self.env.step(actions)
        self.steps += 1
        now = time.monotonic()
        if self._pending_step is not None and (self._event is None or self._event.query()):
            self.publish(self._pending_step)
        if now >= self._next and self._pending_step is None:
            self._next = now + self.period
            self.sample(out.obs, actions, out.info)
            if self._event is None:
                self.publish(self.steps * self.env.n_actors)
        self.publish_s += time.monotonic() - now
        return out

    def sample(
        self, obs: torch.Tensor, actions: torch.Tensor, info: dict[str, torch.Tensor] | None = None
    ) -> None:
        """Start copying actor 0's observation and pose and all actions to the host buffers."""
        self._obs_host.copy_(obs[:1], non_blocking=True)
        self._act_host.copy_(actions, non_blocking=True)
        position = (info or {}).get("position")  # (N, 3) meters
        self._has_pose = position is not None
        if position is not None:
            self._pose_host[:3].copy_(position[0], non_blocking=True)
            yaw = getattr(self.env, "yaw", None)  # (N,) radians (the drone env)
            if isinstance(yaw, torch.Tensor):
                self._pose_host[3:4].copy_(yaw[:1], non_blocking=True)
            scene = (info or {}).get("scene_id")  # (N,) int64
            if scene is not None:
                self._pose_host[4:5].copy_(scene[:1], non_blocking=True)
        self._pending_step = self.steps * self.env.n_actors
        if self._event is not None:
            self._event.record()

    def publish(self, step: int) -> None:
        """Queue the copied sample (the buffers are reused, so the messages get their own copies)."""
        first = self._obs_host.numpy().copy()  # (1, 3, Az, El) float32
        acts = self._act_host.numpy().copy()  # (N, 4) float32
        frame = distance_matrix(first, np.zeros(1, np.int32), step, self.run_id)
        self.pubs.observations.publish(frame)
        self.pubs.actions.publish(action_message(acts, step, self.run_id))
        if self._has_pose:
            x, y, z, yaw, scene = (float(v) for v in self._pose_host.tolist())
            self.pubs.poses.publish(
                RobotPose(env_id=0, x=x, y=y, z=z, roll=0.0, pitch=0.0, yaw=yaw, timestamp=frame.timestamp)
            )
            if self.on_pose is not None:
                self.on_pose(int(scene), z)
        self.last_observation, self.last_publish = frame, time.monotonic()
        self._pending_step = None


class FrameRepeater:
    """Keeps actor 0's observation stream at the tap's rate while the loop steps no env (PPO updates).

    Once per period, when the tap has queued no frame for 1.5 periods (a gap, not jitter), its last
    frame is queued again, unchanged: same step id and timestamp, so a dashboard's freshness shows the
    frame's true age. A daemon thread; `close()` stops it.
    """

    def __init__(self, tap: TelemetryTap, pubs: MeshPublishers) -> None:
        self.tap, self.pubs = tap, pubs
        self.repeats = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="navi-frame-repeater", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = self.tap.period
        while not self._stop.wait(period):
            frame = self.tap.last_observation
            if frame is not None and time.monotonic() - self.tap.last_publish >= 1.5 * period:
                self.pubs.observations.publish(frame)
                self.repeats += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)


PLAN_CELLS = 128
"""Cells on the long side of a floor plan."""
PLAN_PERIOD_S = 5.0
"""A floor plan is published again this often (for dashboards that connect late)."""


def floor_plan(corpus: Any, scene: int, z: float, cells: int = PLAN_CELLS, run_id: str = "") -> FloorPlan:
    """The clearance on the horizontal slice at height z of one scene of a SceneCorpus, over its
    geometry's x-y bounds, `cells` cells on the long side."""
    from navi_env.tracer.trace import sample_distance

    info = corpus.infos[scene]
    lo, hi = np.asarray(info.bounds_min, np.float64), np.asarray(info.bounds_max, np.float64)  # (3,) m
    extent = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1e-3)
    cell = extent / cells
    w = max(1, min(cells, math.ceil((hi[0] - lo[0]) / cell)))
    h = max(1, min(cells, math.ceil((hi[1] - lo[1]) / cell)))
    xs = lo[0] + (np.arange(w) + 0.5) * cell  # (W,) m
    ys = lo[1] + (np.arange(h) + 0.5) * cell  # (H,) m
    gx, gy = np.meshgrid(xs, ys)  # (H, W) each
    points = np.stack([gx, gy, np.full_like(gx, z)], axis=-1).reshape(-1, 3)  # (H*W, 3) m
    dev = corpus.device
    ids = torch.full((points.shape[0],), scene, dtype=torch.int64, device=dev)  # (H*W,)
    pts = torch.from_numpy(points.astype(np.float32)).to(dev).contiguous()  # (H*W, 3)
    clearance = sample_distance(corpus, ids, pts).cpu().numpy().reshape(h, w)  # (H, W) float32 m
    return FloorPlan(
        scene=info.name,
        run_id=run_id,
        origin_x=float(lo[0]),
        origin_y=float(lo[1]),
        cell_size=cell,
        z=float(z),
        clearance=np.ascontiguousarray(clearance, dtype=np.float32),
        timestamp=time.time(),
    )


class FloorPlanner:
    """Publishes the floor plan of actor 0's scene from a daemon thread: computed when the scene
    changes (or the drone's height moved more than a meter), sent again every PLAN_PERIOD_S."""

    def __init__(self, corpus: Any, pubs: MeshPublishers, run_id: Callable[[], str]) -> None:
        self.corpus, self.pubs, self.run_id = corpus, pubs, run_id
        self.plans = 0  # floor plans computed
        self._want: tuple[int, float] | None = None
        self._plan: FloorPlan | None = None
        self._key: tuple[int, float] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="navi-floor-plan", daemon=True)
        self._thread.start()

    def request(self, scene: int, z: float) -> None:
        """Actor 0 is in `scene` at height z (called with every published pose; cheap)."""
        self._want = (scene, z)
        key = self._key
        if key is None or key[0] != scene or abs(key[1] - z) > 1.0:
            self._wake.set()

    def _run(self) -> None:
        last_sent = 0.0
        while not self._stop.is_set():
            self._wake.wait(PLAN_PERIOD_S)
            self._wake.clear()
            if self._stop.is_set():
                return
            want, key = self._want, self._key
            if want is not None and (key is None or key[0] != want[0] or abs(key[1] - want[1]) > 1.0):
                try:
                    self._plan = floor_plan(self.corpus, want[0], want[1], run_id=self.run_id())
                except (RuntimeError, ValueError, IndexError, TypeError) as err:
                    log.warning("floor plan of scene %d failed: %s", want[0], err)
                    self._key = want  # not again for this scene and height
                    continue
                self._key = want
                self.plans += 1
                last_sent = 0.0
            if self._plan is not None and time.monotonic() - last_sent >= min(1.0, PLAN_PERIOD_S):
                self.pubs.floor_plans.publish(self._plan)
                last_sent = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5.0)


def telemetry_rows(prefix: str, row: dict[str, float], run_id: str) -> list[TelemetryEvent]:
    """A log row -> one TelemetryEvent per finite value, keyed `<prefix>.<name>`."""
    step = int(row.get("step", 0))
    return [
        telemetry(f"{prefix}.{name}", value, step, run_id)
        for name, value in row.items()
        if name != "step" and np.isfinite(value)
    ]


class TrainingMetrics:
    """on_log callback of `train`: Prometheus gauges and counters plus `actor.training.*` telemetry."""

    def __init__(
        self,
        pubs: MeshPublishers,
        tap: TelemetryTap,
        device: torch.device,
        status: ServiceStatus | None = None,
        world: int = 1,
    ) -> None:
        self.pubs, self.tap, self.device, self.status = pubs, tap, device, status
        self.world = world  # data-parallel ranks stepping as many actors as this one, in lockstep
        self.counted_steps = 0  # actor-steps of this run already added to navi_steps_total
        self.t0 = time.monotonic()

    def __call__(self, run_id: str, row: dict[str, float]) -> None:
        taken = self.tap.steps * self.tap.n_actors * self.world
        metrics.STEPS.labels("train").inc(taken - self.counted_steps)
        self.counted_steps = taken
        metrics.EPISODES.labels("train").inc(max(0.0, row.get("episodes", 0.0)))  # this log window's
        metrics.STEPS_PER_SECOND.labels("train").set(row.get("sps", 0.0))
        metrics.REWARD_EMA.set(row.get("reward_ema", 0.0))
        for name, value in row.items():
            if "loss" in name or name in ("entropy", "approx_kl", "kl"):
                metrics.LOSS.labels(name).set(value)
        metrics.record_gpu_memory(self.device)
        metrics.PUBLISH_SECONDS.inc(self.tap.publish_s)
        extra = {"publish_fraction": self.tap.publish_s / max(time.monotonic() - self.t0, 1e-9)}
        if self.status is not None:
            self.status.update(step=int(row.get("step", 0)))
        for event in telemetry_rows("actor.training", {**row, **extra}, run_id):
            self.pubs.telemetry.publish(event)
        self.tap.publish_s, self.t0 = 0.0, time.monotonic()


class ServiceStatus:
    """What /healthz says beyond liveness: phase, run, actors and the corpus build (thread-safe)."""

    def __init__(self, corpus: Path | None) -> None:
        self._lock = threading.Lock()
        self.phase = "starting"
        self.step = 0  # step id of the newest training log row
        self.start_step = 0  # step id the run resumed from (0: from scratch)
        self.run_id = ""
        self.actors = 0
        self.corpus_path = str(corpus) if corpus is not None else ""
        self.corpus: BuildProgress | None = BuildProgress("missing") if corpus is not None else None

    def update(self, **fields: Any) -> None:
        with self._lock:
            for name, value in fields.items():
                setattr(self, name, value)

    def __call__(self) -> dict[str, Any]:
        with self._lock:
            corpus = None
            if self.corpus is not None:
                c = self.corpus
                corpus = {
                    "path": self.corpus_path,
                    "state": c.state,
                    "scenes_ready": c.scenes_ready,
                    "scenes_total": c.scenes_total,
                    "rejected": c.rejected,
                    "error": c.error,
                }
            return {
                "phase": self.phase,
                "run_id": self.run_id,
                "actors": self.actors,
                "step": self.step,
                "start_step": self.start_step,
                "corpus": corpus,
            }


class CorpusReporter:
    """Turns corpus build progress into /healthz status, navi_corpus_* gauges and `corpus.*` telemetry."""

    def __init__(self, status: ServiceStatus, pubs: MeshPublishers) -> None:
        self.status, self.pubs = status, pubs

    def __call__(self, progress: BuildProgress) -> None:
        self.status.update(corpus=progress)
        metrics.CORPUS_SCENES_READY.set(progress.scenes_ready)
        metrics.CORPUS_SCENES_PLANNED.set(progress.scenes_total)
        metrics.CORPUS_SCENES_REJECTED.set(progress.rejected)
        metrics.CORPUS_READY.set(1.0 if progress.state == "ready" else 0.0)
        self.publish(progress)
        log.info(
            "corpus %s: %d/%d scenes ready, %d rejected%s",
            progress.state,
            progress.scenes_ready,
            progress.scenes_total,
            progress.rejected,
            f" ({progress.error})" if progress.error else "",
        )

    def publish(self, progress: BuildProgress) -> None:
        for key, value in (
            (keys.CORPUS_SCENES_READY, progress.scenes_ready),
            (keys.CORPUS_SCENES_PLANNED, progress.scenes_total),
            (keys.CORPUS_SCENES_REJECTED, progress.rejected),
            (keys.CORPUS_READY, 1.0 if progress.state == "ready" else 0.0),
        ):
            self.pubs.telemetry.publish(telemetry(key, float(value), 0))


def prepare_corpus(
    cfg: LearnerServiceConfig,
    sess: zenoh.Session,
    reporter: CorpusReporter,
    stop: threading.Event,
) -> None:
    """Make sure the sdfdag corpus exists: read its manifest, or build the procedural default corpus
    (over compile jobs, or in this process with corpus_build="local")."""
    if cfg.env_kind != "sdfdag":
        return
    from navi_env.corpus.folder import MANIFEST, CorpusError, build_default_corpus, read_manifest

    if not (cfg.corpus / MANIFEST).is_file():
        reporter.status.update(phase="corpus")
        if cfg.corpus_build == "local":
            log.info("building the procedural default corpus into %s in this process", cfg.corpus)
            reporter(BuildProgress("building", scenes_total=cfg.corpus_scenes))
            build_default_corpus(
                cfg.corpus, cfg.corpus_resolution, cfg.corpus_scenes, cfg.train.seed, cfg.train.device
            )
        else:
            log.info(
                "building the procedural default corpus into %s over compile jobs (%d scenes at %d^3)",
                cfg.corpus,
                cfg.corpus_scenes,
                cfg.corpus_resolution,
            )
            build = CorpusBuildConfig(
                cfg.corpus, cfg.corpus_scenes, cfg.corpus_resolution, cfg.train.seed, cfg.train.device
            )
            build_corpus_over_jobs(build, sess, reporter, stop)
    try:
        manifest = read_manifest(cfg.corpus)
    except CorpusError as err:
        reporter(BuildProgress("failed", error=str(err)))
        raise
    total = len(manifest.scenes) + len(manifest.rejected)
    reporter(BuildProgress("ready", len(manifest.scenes), total, len(manifest.rejected)))


class Heartbeat:
    """Once a second: `actor.<mode>.actors` while the loop runs (mode and actor count for dashboards),
    and the corpus progress again while it is built (for dashboards that connect late)."""

    def __init__(self, status: ServiceStatus, pubs: MeshPublishers, reporter: CorpusReporter) -> None:
        self.status, self.pubs, self.reporter = status, pubs, reporter
        self.tap: TelemetryTap | None = None  # set once the environment exists (its step count)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="navi-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            phase, actors, run_id = self.status.phase, self.status.actors, self.status.run_id
            if phase in ("training", "inference") and actors > 0:
                prefix = keys.TRAINING if phase == "training" else keys.INFERENCE
                step = self.status.step
                if phase == "inference" and self.tap is not None:
                    step = self.tap.steps * self.tap.n_actors
                self.pubs.telemetry.publish(telemetry(prefix + keys.ACTORS, actors, step, run_id))
            corpus = self.status.corpus
            if phase == "corpus" and corpus is not None:
                self.reporter.publish(corpus)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)


def run_training(
    cfg: LearnerServiceConfig,
    env: TelemetryTap,
    pubs: MeshPublishers,
    status: ServiceStatus,
    dist: Dist | None = None,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    """`train` with the tap and the metrics callback; returns the run summary. Rank 0 of a
    data-parallel learner passes its Dist and the stop event (signals end training through it)."""
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
        should_stop=stop.is_set if d.active and stop is not None else None,
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
    policy = CheckpointPolicy(path, device, cfg.deterministic)
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
                policy = CheckpointPolicy(path, device, cfg.deterministic)
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
        corpus, n, cfg.train.device, cfg.train.seed + d.rank, cfg.env_kind, rank=d.rank, world=d.world
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
        )
        tap = TelemetryTap(base_env, pubs, cfg.observation_hz)
        heartbeat.tap = tap
        repeater = FrameRepeater(tap, pubs)
        scenes = getattr(base_env, "corpus", None)
        if scenes is not None:
            planner = FloorPlanner(scenes, pubs, lambda: tap.run_id)
            tap.on_pose = planner.request
        if cfg.mode == "train":
            summary = run_training(cfg, tap, pubs, status, d, stop)
        else:
            summary = run_inference(cfg, tap, pubs, sess, stop, status)
        status.update(phase="done")
        repeater.close()  # the run is over: no frame is repeated as if it were live
        log.info("run finished: %s", json.dumps(summary, default=str))
        if not cfg.exit_when_done:
            try:
                stop.wait()
            except KeyboardInterrupt:
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
