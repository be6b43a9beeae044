"""The dashboard's state machine: what the page shows, derived only from decoded messages.

Nothing here knows about Zenoh or HTTP: a feed calls `on_telemetry` / `on_observation` (from any thread)
and the hub calls `snapshot` at its push rate. That is what makes the core testable in-process.

Modes: WAITING (no stream has spoken within `stale_after_s`), TRAINING (the newest fresh `actor.*`
telemetry is `actor.training.*`), INFERENCE (`actor.inference.*`), OBSERVER (streams are live but no
actor telemetry is fresh).

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

from navi_contracts.models import DistanceMatrix, TelemetryEvent


class Mode(StrEnum):
    WAITING = "WAITING"
    TRAINING = "TRAINING"
    INFERENCE = "INFERENCE"
    OBSERVER = "OBSERVER"


TRAINING_PREFIX = "actor.training."
INFERENCE_PREFIX = "actor.inference."


@dataclass(frozen=True)
class DashboardConfig:
    """What the dashboard reads from telemetry and how long it remembers."""

    stale_after_s: float = 5.0
    """A stream with nothing newer than this many seconds counts as gone (the page falls back to WAITING)."""
    history: int = 300
    """Points kept per chart series (oldest dropped)."""
    max_series: int = 8
    """Most telemetry keys charted per chart; later new keys are ignored (bounds memory on odd keys)."""
    sps_names: tuple[str, ...] = ("sps",)
    """Last key component(s) charted as steps per second and shown in the status bar."""
    reward_names: tuple[str, ...] = ("reward_ema", "reward_mean", "episode_return", "reward")
    """Last key component(s) charted as reward."""
    actor_count_names: tuple[str, ...] = ("actors", "n_actors", "active_actors")
    """Last key component(s) read as the active actor count."""


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
    actors: int | None = None
    actors_at: float = -float("inf")
    run_id: str = ""
    step: int = 0


@dataclass
class DashboardState:
    """Thread-safe dashboard state; every input is a decoded contract message."""

    config: DashboardConfig = field(default_factory=DashboardConfig)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _seen: _Seen = field(default_factory=_Seen, repr=False)
    _frame: Frame | None = field(default=None, repr=False)
    _frames: int = 0
    _rejected: int = 0
    _decode_errors: int = 0
    _reward: dict[str, Series] = field(default_factory=dict, repr=False)
    _sps: dict[str, Series] = field(default_factory=dict, repr=False)

    def on_telemetry(self, event: TelemetryEvent, now: float | None = None) -> None:
        """Feed one telemetry event (any thread)."""
        at = time.monotonic() if now is None else now
        name = event.key.rsplit(".", 1)[-1]
        with self._lock:
            seen = self._seen
            seen.last_telemetry = at
            seen.run_id = event.run_id or seen.run_id
            seen.step = event.step
            if event.key.startswith(TRAINING_PREFIX):
                seen.last_training = at
            elif event.key.startswith(INFERENCE_PREFIX):
                seen.last_inference = at
            if not np.isfinite(event.value):
                return
            if name in self.config.sps_names:
                seen.sps, seen.sps_at = event.value, at
                self._append(self._sps, event)
            elif name in self.config.reward_names:
                self._append(self._reward, event)
            elif name in self.config.actor_count_names and event.value >= 0:
                seen.actors, seen.actors_at = int(event.value), at

    def on_observation(self, matrix: DistanceMatrix, now: float | None = None) -> None:
        """Feed one observation (any thread); keeps only actor 0's forward hemisphere of the newest."""
        at = time.monotonic() if now is None else now
        if matrix.n_envs < 1 or matrix.azimuth_bins < 4 or matrix.azimuth_bins % 4:
            with self._lock:
                self._rejected += 1
            return
        pixels = quantise(forward_hemisphere(matrix.depth[0]))  # (El, Az/2) uint8
        with self._lock:
            self._seen.last_observation = at
            self._frames += 1
            self._frame = Frame(pixels, matrix.step_id, matrix.run_id, matrix.n_envs, at, self._frames)

    def set_decode_errors(self, count: int) -> None:
        """The feed's count of payloads that failed to decode (added to `rejected` on the page)."""
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
            frame = self._frame if self._frame is not None and at - self._frame.received <= stale else None
            actors = seen.actors if at - seen.actors_at <= stale else (frame.n_envs if frame else None)
            return Snapshot(
                mode=self._mode(at),
                frame=frame,
                obs_age_ms=None if frame is None else max(0.0, (at - frame.received) * 1000.0),
                sps=seen.sps if at - seen.sps_at <= stale else None,
                actors=actors,
                run_id=seen.run_id,
                step=seen.step,
                frames=self._frames,
                rejected=self._rejected + self._decode_errors,
                reward={k: list(s.points) for k, s in self._reward.items()},
                sps_history={k: list(s.points) for k, s in self._sps.items()},
            )


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
    rejected: int  # unusable observations plus payloads that failed to decode
    reward: dict[str, list[tuple[int, float]]]
    sps_history: dict[str, list[tuple[int, float]]]
