"""`navi record`: Zenoh streams into an appendable Zarr v3 store (layout in docs/AUDITOR.md).

Per topic group `<name>/` (time-first arrays, T messages):
    t       (T,)  float64  seconds since the session started (receive time)
    offset  (T,)  int64    start of the message in `data`
    length  (T,)  int64    bytes of the message
    data    (B,)  uint8    the raw msgpack payloads, back to back (exactly what was on the wire)
The telemetry group also has decoded columns `key` (T,) str, `value` (T,) float64, `step` (T,) int64.
The `episodes/` group indexes episode ends seen in telemetry (keys ending in `.episode_return`):
    t (E,) float64, step (E,) int64, value (E,) float64 (the return), row (E,) int64 (observation rows
    recorded before it), run_id (E,) str.

Writes are buffered in memory and flushed every `flush_interval_s` (or `flush_rows` messages). A flush
writes the new rows, then records the committed counts in the group's attributes (`rows`, `bytes`) in
one metadata write; zarr replaces each file atomically, so a recorder killed at any instant leaves every
committed row readable, and readers never look past `rows`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

import numpy as np

from navi_contracts.codec import ContractError, decode
from navi_contracts.models import TelemetryEvent

FORMAT = "navi-session"
FORMAT_VERSION = 1
EPISODES = "episodes"
TELEMETRY = "telemetry"
OBSERVATIONS = "observations"
EPISODE_END_NAME = "episode_return"
INDEX_COLUMNS: tuple[tuple[str, Any], ...] = (("t", "float64"), ("offset", "int64"), ("length", "int64"))
"""Per-message columns of every topic group (plus the `data` byte array)."""
TELEMETRY_COLUMNS: tuple[tuple[str, Any], ...] = (("key", str), ("value", "float64"), ("step", "int64"))
"""Decoded columns of the telemetry group (`str` is Zarr's variable-length UTF-8 string)."""
EPISODE_COLUMNS: tuple[tuple[str, Any], ...] = (
    ("t", "float64"),
    ("step", "int64"),
    ("value", "float64"),
    ("row", "int64"),
    ("run_id", str),
)
"""Columns of the episode index."""


@dataclass(frozen=True)
class RecorderConfig:
    """Buffering and chunking of a recording."""

    flush_interval_s: float = 1.0
    """Longest time a received message waits in memory before it is written."""
    flush_rows: int = 512
    """A topic's buffer is written as soon as it holds this many messages."""
    chunk_rows: int = 4096
    """Rows per chunk of the per-message arrays (t, offset, length, decoded columns)."""
    chunk_bytes: int = 1 << 20
    """Bytes per chunk of a topic's payload array."""


@dataclass
class _Buffer:
    t: list[float] = field(default_factory=list)
    payloads: list[bytes] = field(default_factory=list)
    events: list[TelemetryEvent] = field(default_factory=list)


def _create(group: Any, name: str, dtype: Any, chunk: int) -> None:
    group.create_array(name, shape=(0,), chunks=(chunk,), dtype=dtype)


def _append(array: Any, values: np.ndarray) -> None:
    start = array.shape[0]
    array.resize((start + values.shape[0],))
    array[start : start + values.shape[0]] = values


class SessionWriter:
    """Appends messages of named topics to a new Zarr v3 session store; thread-safe `append`."""

    def __init__(self, path: Path, topics: dict[str, str], config: RecorderConfig | None = None) -> None:
        import zarr

        self.path = path
        self.config = config or RecorderConfig()
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._start = time.monotonic()
        self._root = cast(Any, zarr.open_group(str(path), mode="w-", zarr_format=3))
        self._root.update_attributes(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "created_at": datetime.now(UTC).isoformat(),
                "start_unix_s": time.time(),
                "topics": topics,
            }
        )
        rows, chunk = self.config.chunk_rows, self.config.chunk_bytes
        for name, key in topics.items():
            group = self._root.create_group(name)
            group.update_attributes({"key": key, "rows": 0, "bytes": 0})
            for column, dtype in INDEX_COLUMNS:
                _create(group, column, dtype, rows)
            _create(group, "data", "uint8", chunk)
            if name == TELEMETRY:
                for column, dtype in TELEMETRY_COLUMNS:
                    _create(group, column, dtype, rows)
        episodes = self._root.create_group(EPISODES)
        episodes.update_attributes({"rows": 0})
        for column, dtype in EPISODE_COLUMNS:
            _create(episodes, column, dtype, rows)
        self._buffers: dict[str, _Buffer] = {name: _Buffer() for name in topics}
        self._episodes: list[tuple[float, int, float, int, str]] = []
        self._observation_rows = 0
        self._last_flush = time.monotonic()
        self.rejected = 0
        self.written = 0

    def now(self) -> float:
        """Seconds since the session started (the `t` of a message received now)."""
        return time.monotonic() - self._start

    def append(self, topic: str, payload: bytes, t: float | None = None) -> None:
        """Buffer one message; telemetry that does not decode is counted and dropped."""
        at = self.now() if t is None else t
        event = None
        if topic == TELEMETRY:
            try:
                event = decode(payload, TelemetryEvent)
            except ContractError:
                with self._lock:
                    self.rejected += 1
                return
        with self._lock:
            buffer = self._buffers[topic]
            buffer.t.append(at)
            buffer.payloads.append(bytes(payload))
            if topic == OBSERVATIONS:
                self._observation_rows += 1
            if event is not None:
                buffer.events.append(event)
                if event.key.rsplit(".", 1)[-1] == EPISODE_END_NAME:
                    self._episodes.append((at, event.step, event.value, self._observation_rows, event.run_id))
            due = len(buffer.t) >= self.config.flush_rows
        if due:
            self.flush()

    def flush_if_due(self) -> None:
        if time.monotonic() - self._last_flush >= self.config.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Write everything buffered, then commit the new row counts."""
        with self._lock:
            buffers, self._buffers = self._buffers, {name: _Buffer() for name in self._buffers}
            episodes, self._episodes = self._episodes, []
        with self._write_lock:
            for name, buffer in buffers.items():
                if buffer.t:
                    self._write_topic(name, buffer)
            if episodes:
                self._write_episodes(episodes)
            self._last_flush = time.monotonic()

    def _write_topic(self, name: str, buffer: _Buffer) -> None:
        group = self._root[name]
        rows, nbytes = int(group.attrs["rows"]), int(group.attrs["bytes"])
        lengths = np.array([len(p) for p in buffer.payloads], dtype=np.int64)  # (T,) int64
        offsets = nbytes + np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)  # (T,) int64
        data = np.frombuffer(b"".join(buffer.payloads), dtype=np.uint8)  # (B,) uint8
        for column, values in (
            ("t", np.asarray(buffer.t, dtype=np.float64)),
            ("offset", offsets),
            ("length", lengths),
            ("data", data),
        ):
            _trim_and_append(group[column], rows if column != "data" else nbytes, values)
        if name == TELEMETRY:
            events = buffer.events
            _trim_and_append(group["key"], rows, np.array([e.key for e in events], dtype=object))
            _trim_and_append(group["value"], rows, np.array([e.value for e in events], dtype=np.float64))
            _trim_and_append(group["step"], rows, np.array([e.step for e in events], dtype=np.int64))
        # One metadata write for both counts (`attrs.update` would write once per key, and a recorder
        # killed between the two left `rows` counting payloads past `bytes`).
        group.update_attributes({"rows": rows + len(buffer.t), "bytes": nbytes + int(lengths.sum())})
        self.written += len(buffer.t)

    def _write_episodes(self, episodes: list[tuple[float, int, float, int, str]]) -> None:
        group = self._root[EPISODES]
        rows = int(group.attrs["rows"])
        t, step, value, row, run_id = zip(*episodes, strict=True)
        _trim_and_append(group["t"], rows, np.asarray(t, dtype=np.float64))
        _trim_and_append(group["step"], rows, np.asarray(step, dtype=np.int64))
        _trim_and_append(group["value"], rows, np.asarray(value, dtype=np.float64))
        _trim_and_append(group["row"], rows, np.asarray(row, dtype=np.int64))
        _trim_and_append(group["run_id"], rows, np.array(run_id, dtype=object))
        group.update_attributes({"rows": rows + len(episodes)})

    def close(self) -> None:
        self.flush()


def _trim_and_append(array: Any, committed: int, values: np.ndarray) -> None:
    """Append after the committed length (rows past it, from an interrupted flush, are overwritten)."""
    if array.shape[0] != committed:
        array.resize((committed,))
    _append(array, values)


def topic_names(topics: Sequence[str]) -> dict[str, str]:
    """`--topics` names -> Zenoh keys; raise ValueError naming the choices for an unknown name."""
    from navi_contracts.topics import ACTIONS, MODEL_PROMOTED
    from navi_contracts.topics import OBSERVATIONS as OBS_TOPIC
    from navi_contracts.topics import TELEMETRY as TELEMETRY_TOPIC

    known = {
        OBSERVATIONS: OBS_TOPIC.key,
        "actions": ACTIONS.key,
        TELEMETRY: TELEMETRY_TOPIC.key,
        "model_promoted": MODEL_PROMOTED.key,
    }
    unknown = [t for t in topics if t not in known]
    if unknown:
        raise ValueError(f"unknown topic(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    return {t: known[t] for t in topics}


def record(
    out: Path,
    topics: dict[str, str],
    duration_s: float | None,
    session: Any,
    config: RecorderConfig | None = None,
    stop: threading.Event | None = None,
    on_ready: Callable[[], None] | None = None,
) -> SessionWriter:
    """Subscribe `session` to `topics` and record until `duration_s` passes or `stop` is set.

    `on_ready` is called once the subscribers are declared (messages from then on are recorded).
    """
    writer = SessionWriter(out, topics, config)
    halt = stop or threading.Event()
    subscribers = [
        session.declare_subscriber(key, lambda s, name=name: writer.append(name, s.payload.to_bytes()))
        for name, key in topics.items()
    ]
    if on_ready is not None:
        on_ready()
    deadline = None if duration_s is None else time.monotonic() + duration_s
    try:
        while not halt.is_set() and (deadline is None or time.monotonic() < deadline):
            halt.wait(min(0.1, writer.config.flush_interval_s))
            writer.flush_if_due()
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        writer.close()
    return writer
