"""`navi serve learner`: training or inference in-process, on the mesh, with the control plane.

The loop is the learner's own (`ppo.train.train`, or the inference loop of loops.py); the service taps
it. This module holds the tap on the loop (TelemetryTap, FrameRepeater, TrainingMetrics, which read
this module's clock); beside it, one module each: the settings (config.py), the publishers
(publishers.py), floor plans (floor_plan.py), bring-up, status and heartbeat (bring_up.py), the
training and inference loops (loops.py), and `serve_learner`, the service itself (shell.py).
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
SIGTERM or Ctrl+C sets the stop event: training ends after the update in progress, with a checkpoint.

Several GPUs (`navi serve learner --nproc N`, run through torchrun; navi_learner/ppo/dist.py): rank 0 is
the service above (control plane, mesh, telemetry, corpus build) and trains its share; every other
rank waits for the corpus, trains its own actors on its own GPU and publishes nothing. A signal sets
the stop event, which ends training after the update in progress on every rank (one checkpoint).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import torch

from navi_contracts.models import DistanceMatrix, RobotPose
from navi_learner.envs.protocol import BatchedEnv, StepLike
from navi_learner.service.bring_up import ServiceStatus
from navi_learner.service.publishers import MeshPublishers, telemetry_rows
from navi_mesh import metrics
from navi_mesh.messages import action_message, distance_matrix


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
