"""The dashboard's state machine: what the page shows, derived only from decoded messages.

Nothing here knows about Zenoh or HTTP: a feed calls `on_telemetry` / `on_observation` / `on_pose` /
`on_floor_plan` (from any thread) and the hub calls `snapshot` at its push rate. That is what makes the
core testable in-process.

Modes: WAITING (no stream has spoken within `stale_after_s`), TRAINING (the newest fresh `actor.*`
telemetry is `actor.training.*`), INFERENCE (`actor.inference.*`), OBSERVER (streams are live but no
actor telemetry is fresh). The learner's once-a-second heartbeat (`actor.<mode>.actors`) keeps its
mode fresh between slow PPO updates; SPS keeps its last value while the stream it came from is fresh.

Freshness of the observation (`obs_age_ms`) is the age of the frame itself: time since its publisher
stamped it (`DistanceMatrix.timestamp`, wall clock), so a frame the learner repeats while it updates
its policy grows older on the page instead of looking new.

Forward hemisphere: observation azimuth bin 0 looks straight ahead and bins grow counter-clockwise seen
from above (toward the drone's left), so the forward half of an Az-bin observation is bins
[-Az/4, Az/4) wrapped. The page draws it with the drone's left on the left (bin Az/4-1 in column 0) and
straight up on the top row (elevation bins run from straight down to straight up).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from navi_contracts import telemetry_keys as keys
from navi_contracts.models import DistanceMatrix, FloorPlan, RobotPose, TelemetryEvent


class Mode(StrEnum):
    WAITING = "WAITING"
    TRAINING = "TRAINING"
    INFERENCE = "INFERENCE"
    OBSERVER = "OBSERVER"


TRAINING_PREFIX = keys.TRAINING
INFERENCE_PREFIX = keys.INFERENCE

CHARTS: dict[str, tuple[str, ...]] = {
    "reward": ("reward_ema", "reward_mean", "reward"),
    "sps": ("sps",),
    "episode_return": ("episode_return",),
    "collisions": ("collisions_per_1k", "obstacle_collisions_per_1k", "drone_collisions_per_1k"),
    "coverage": ("coverage_per_1k",),
    "entropy": ("entropy",),
    "value_loss": ("value_loss",),
}
"""Chart id -> the last key components charted on it (the learner's log-row column names)."""


@dataclass(frozen=True)
class DashboardConfig:
    """What the dashboard reads from telemetry and how long it remembers."""

    stale_after_s: float = 5.0
    """A stream with nothing newer than this many seconds counts as gone (the page falls back to WAITING)."""
    history: int = 300
    """Points kept per chart series (oldest dropped)."""
    max_series: int = 8
    """Most telemetry keys charted per chart; later new keys are ignored (bounds memory on odd keys)."""
    charts: dict[str, tuple[str, ...]] = field(default_factory=lambda: dict(CHARTS))
    """Chart id -> last key component(s) charted on it; the `sps` chart's newest value is the status bar's."""
    actor_count_names: tuple[str, ...] = ("actors", "n_actors", "active_actors")
    """Last key component(s) read as the active actor count."""
    trail: int = 600
    """Poses kept in actor 0's trail (oldest dropped; the trail restarts when the scene changes)."""


def forward_indices(azimuth_bins: int) -> np.ndarray:
    """Azimuth bins of the forward hemisphere in display order (drone's left first): (Az/2,) int64."""
    quarter = azimuth_bins // 4
    half = azimuth_bins // 2
    return (quarter - 1 - np.arange(half)) % azimuth_bins  # (Az/2,) int64


def forward_hemisphere(depth: np.ndarray) -> np.ndarray:
    """Actor-0 depth (Az, El) -> display image (El, Az/2): row 0 straight up, column 0 the drone's left."""
    image = depth[forward_indices(depth.shape[0])]  # (Az/2, El)
    return np.ascontiguousarray(image.T[::-1])  # (El, Az/2)


def forward_hemisphere_ref(depth: np.ndarray) -> np.ndarray:
    """Slow, obviously correct twin of `forward_hemisphere` (one pixel at a time)."""
    az, el = depth.shape
    half = az // 2
    image = np.empty((el, half), dtype=depth.dtype)  # (El, Az/2)
    for row in range(el):
        for col in range(half):
            azimuth_bin = (az // 4 - 1 - col) % az  # column 0 = leftmost = most counter-clockwise bin
            image[row, col] = depth[azimuth_bin, el - 1 - row]
    return image


LOG_SPREAD = 99.0
"""Depth is shown on the scale log(1 + 99 d) / log(100): at a 100 m horizon 1 m reads 0.15, 5 m 0.39,
20 m 0.66, so the near field that matters for flying gets most of the palette."""


def quantise(image: np.ndarray) -> np.ndarray:
    """Normalised depth in [0, 1] -> uint8 on the log display scale (0 = touching, 255 = horizon).

    NaN reads as 0 (the page never shows a hole as open space).
    """
    clean = np.clip(np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)  # (El, Az/2) float32
    scaled = np.log1p(clean * LOG_SPREAD) / np.log1p(LOG_SPREAD)  # (El, Az/2) in [0, 1]
    return np.rint(scaled * 255.0).astype(np.uint8)  # (El, Az/2) uint8


@dataclass
class Frame:
    """The latest displayable observation."""

    pixels: np.ndarray  # (El, Az/2) uint8
    step_id: int
    run_id: str
    n_envs: int
    received: float  # time.monotonic() at arrival
    seq: int  # increases by one per accepted frame
    stamp: float = 0.0  # DistanceMatrix.timestamp (publisher's wall clock)
    lag: float = 0.0  # seconds between the stamp and the arrival (>= 0)


PLAN_FREE_M = 2.0
"""Clearance drawn at full brightness on the floor plan (meters); walls (<= 0) are black."""


def plan_image(clearance: np.ndarray) -> np.ndarray:
    """Floor-plan clearance (H, W) meters -> uint8 (H, W): 0 inside geometry, 64..255 free (by clearance)."""
    c = np.nan_to_num(clearance, nan=0.0, posinf=PLAN_FREE_M, neginf=0.0)  # (H, W)
    free = np.clip(c / PLAN_FREE_M, 0.0, 1.0)  # (H, W)
    return np.where(c > 0.0, np.rint(64.0 + 191.0 * free), 0.0).astype(np.uint8)  # (H, W)


@dataclass(frozen=True)
class Plan:
    """The floor plan of actor 0's scene, ready to draw (row 0 = the smallest y)."""

    scene: str
    pixels: np.ndarray  # (H, W) uint8, plan_image
    origin_x: float
    origin_y: float
    cell_size: float
    z: float
    seq: int


@dataclass(frozen=True)
class Corpus:
    """The corpus build as the learner reports it (corpus.* telemetry)."""

    ready: int
    planned: int
    rejected: int
    done: bool


@dataclass
class Series:
    """One charted telemetry key: (step, value) pairs, oldest first."""

    points: deque[tuple[int, float]]


@dataclass
class _Seen:
    last_telemetry: float = -float("inf")
    last_observation: float = -float("inf")
    last_training: float = -float("inf")
    last_inference: float = -float("inf")
    sps: float | None = None
    sps_at: float = -float("inf")
    sps_prefix: str = ""
    actors: int | None = None
    actors_at: float = -float("inf")
    run_id: str = ""
    step: int = 0
    corpus: dict[str, float] = field(default_factory=dict)
    corpus_at: float = -float("inf")


@dataclass
class DashboardState:
    """Thread-safe dashboard state; every input is a decoded contract message."""

    config: DashboardConfig = field(default_factory=DashboardConfig)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _seen: _Seen = field(default_factory=_Seen, repr=False)
    _frame: Frame | None = field(default=None, repr=False)
    _frames: int = 0
    _bad_frames: int = 0
    _decode_errors: int = 0
    _charts: dict[str, dict[str, Series]] = field(default_factory=dict, repr=False)
    _trail: deque[tuple[float, float]] = field(default_factory=deque, repr=False)
    _pose: RobotPose | None = field(default=None, repr=False)
    _pose_at: float = -float("inf")
    _plan: Plan | None = field(default=None, repr=False)
    _chart_of: dict[str, str] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self._charts = {chart: {} for chart in self.config.charts}
        self._chart_of = {name: chart for chart, names in self.config.charts.items() for name in names}
        self._trail = deque(maxlen=self.config.trail)

    def on_telemetry(self, event: TelemetryEvent, now: float | None = None) -> None:
        """Feed one telemetry event (any thread)."""
        at = time.monotonic() if now is None else now
        name = event.key.rsplit(".", 1)[-1]
        with self._lock:
            seen = self._seen
            seen.last_telemetry = at
            if event.key.startswith(keys.CORPUS):
                if np.isfinite(event.value):
                    seen.corpus[event.key] = event.value
                    seen.corpus_at = at
                return
            seen.run_id = event.run_id or seen.run_id
            seen.step = event.step
            if event.key.startswith(TRAINING_PREFIX):
                seen.last_training = at
            elif event.key.startswith(INFERENCE_PREFIX):
                seen.last_inference = at
            if not np.isfinite(event.value):
                return
            if name in self.config.actor_count_names:
                if event.value >= 0:
                    seen.actors, seen.actors_at = int(event.value), at
                return
            chart = self._chart_of.get(name)
            if chart == "sps":
                seen.sps, seen.sps_at = event.value, at
                seen.sps_prefix = event.key[: -len(name)]
            if chart is not None:
                self._append(self._charts[chart], event)

    def on_observation(
        self, matrix: DistanceMatrix, now: float | None = None, wall: float | None = None
    ) -> None:
        """Feed one observation (any thread); keeps only actor 0's forward hemisphere of the newest.

        A frame repeated by its publisher (same step id and stamp as the one shown) keeps the stream
        alive but is not a new frame."""
        at = time.monotonic() if now is None else now
        lag = max(0.0, (time.time() if wall is None else wall) - matrix.timestamp)
        if matrix.n_envs < 1 or matrix.azimuth_bins < 4 or matrix.azimuth_bins % 4:
            with self._lock:
                self._bad_frames += 1
            return
        with self._lock:
            self._seen.last_observation = at
            shown = self._frame
            if shown is not None and (shown.step_id, shown.stamp) == (matrix.step_id, matrix.timestamp):
                return
        pixels = quantise(forward_hemisphere(matrix.depth[0]))  # (El, Az/2) uint8
        with self._lock:
            self._frames += 1
            self._frame = Frame(
                pixels,
                matrix.step_id,
                matrix.run_id,
                matrix.n_envs,
                at,
                self._frames,
                matrix.timestamp,
                lag,
            )

    def on_pose(self, pose: RobotPose, now: float | None = None) -> None:
        """Feed actor 0's pose (other actors' poses are ignored): extends the trail."""
        if pose.env_id != 0:
            return
        at = time.monotonic() if now is None else now
        with self._lock:
            self._pose, self._pose_at = pose, at
            self._seen.last_observation = max(self._seen.last_observation, at)
            self._trail.append((pose.x, pose.y))

    def on_floor_plan(self, plan: FloorPlan, now: float | None = None) -> None:
        """Feed the floor plan of actor 0's scene; a different scene restarts the trail."""
        pixels = plan_image(plan.clearance)  # (H, W) uint8
        with self._lock:
            old = self._plan
            if old is not None and old.scene != plan.scene:
                self._trail.clear()
            same = (
                old is not None
                and old.scene == plan.scene
                and old.pixels.shape == pixels.shape
                and (old.origin_x, old.origin_y, old.cell_size, old.z)
                == (plan.origin_x, plan.origin_y, plan.cell_size, plan.z)
                and np.array_equal(old.pixels, pixels)
            )
            if not same:
                seq = 1 if old is None else old.seq + 1
                self._plan = Plan(
                    plan.scene, pixels, plan.origin_x, plan.origin_y, plan.cell_size, plan.z, seq
                )

    def set_decode_errors(self, count: int) -> None:
        """The feed's count of payloads that failed to decode (shown apart from bad frames and from the
        corpus's rejected scenes)."""
        with self._lock:
            self._decode_errors = count

    def _append(self, table: dict[str, Series], event: TelemetryEvent) -> None:
        series = table.get(event.key)
        if series is None:
            if len(table) >= self.config.max_series:
                return
            series = table[event.key] = Series(deque(maxlen=self.config.history))
        series.points.append((event.step, float(event.value)))

    def mode(self, now: float) -> Mode:
        with self._lock:
            return self._mode(now)

    def _mode(self, now: float) -> Mode:
        seen, stale = self._seen, self.config.stale_after_s
        training = now - seen.last_training <= stale
        inference = now - seen.last_inference <= stale
        if training or inference:
            newest_training = seen.last_training >= seen.last_inference
            return Mode.TRAINING if training and (newest_training or not inference) else Mode.INFERENCE
        if now - seen.last_telemetry <= stale or now - seen.last_observation <= stale:
            return Mode.OBSERVER
        return Mode.WAITING

    def snapshot(self, now: float | None = None) -> Snapshot:
        """Everything the page needs at `now` (time.monotonic() clock)."""
        at = time.monotonic() if now is None else now
        with self._lock:
            seen, stale = self._seen, self.config.stale_after_s
            frame = self._frame if self._frame is not None and at - seen.last_observation <= stale else None
            actors = seen.actors if at - seen.actors_at <= stale else (frame.n_envs if frame else None)
            corpus = None
            if seen.corpus and at - seen.corpus_at <= 10 * stale:
                c = seen.corpus
                corpus = Corpus(
                    int(c.get(keys.CORPUS_SCENES_READY, 0)),
                    int(c.get(keys.CORPUS_SCENES_PLANNED, 0)),
                    int(c.get(keys.CORPUS_SCENES_REJECTED, 0)),
                    c.get(keys.CORPUS_READY, 0.0) >= 1.0,
                )
            pose = self._pose if self._pose is not None and at - self._pose_at <= stale else None
            return Snapshot(
                mode=self._mode(at),
                frame=frame,
                obs_age_ms=None if frame is None else (at - frame.received + frame.lag) * 1000.0,
                sps=seen.sps if self._sps_fresh(at) else None,
                actors=actors,
                run_id=seen.run_id,
                step=seen.step,
                frames=self._frames,
                bad_frames=self._bad_frames,
                decode_errors=self._decode_errors,
                charts={c: {k: list(s.points) for k, s in t.items()} for c, t in self._charts.items()},
                corpus=corpus,
                pose=pose,
                trail=list(self._trail),
                plan=self._plan,
            )

    def _sps_fresh(self, at: float) -> bool:
        """SPS is shown while it is recent, or while the actor stream it came from is fresh."""
        seen, stale = self._seen, self.config.stale_after_s
        if at - seen.sps_at <= stale:
            return True
        if seen.sps_prefix == TRAINING_PREFIX:
            return at - seen.last_training <= stale
        if seen.sps_prefix == INFERENCE_PREFIX:
            return at - seen.last_inference <= stale
        return False


@dataclass(frozen=True)
class Snapshot:
    """A consistent view of the state at one instant."""

    mode: Mode
    frame: Frame | None
    obs_age_ms: float | None
    sps: float | None
    actors: int | None
    run_id: str
    step: int
    frames: int
    bad_frames: int  # observations decoded but unusable (no centred forward half to draw)
    decode_errors: int  # payloads on the mesh that failed to decode
    charts: dict[str, dict[str, list[tuple[int, float]]]]  # chart id -> key -> (step, value), oldest first
    corpus: Corpus | None = None
    pose: RobotPose | None = None  # actor 0's newest pose (None when stale)
    trail: list[tuple[float, float]] = field(default_factory=list)  # actor 0's (x, y) meters, oldest first
    plan: Plan | None = None

    @property
    def reward(self) -> dict[str, list[tuple[int, float]]]:
        return self.charts.get("reward", {})

    @property
    def sps_history(self) -> dict[str, list[tuple[int, float]]]:
        return self.charts.get("sps", {})
