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

A writer holds an exclusive flock on the store's folder while it is open and, once every received message
is written, marks the store closed (root attribute `closed_at`). A flush that fails (OSError: a full
disk) is counted in navi_write_errors_total{what="recording"} and logged once; its messages stay in
memory (up to `max_pending_bytes`; later ones are dropped and counted) and the next flush writes them,
over the rows the failed one left past the committed counts. At start `record` checks the stores next to
the new one (`recover_recordings`): a store no writer holds and not marked closed is cut back to its
committed rows (partial chunk files of zarr's interrupted writes removed) and marked closed; one whose
metadata does not read is renamed to `<name>.corrupt-<UTC time>`. Each gets one log line.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
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
from navi_mesh.metrics import WRITE_ERRORS

log = logging.getLogger(__name__)

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
    max_pending_bytes: int = 256 << 20
    """Payload bytes held in memory while writes fail (a full disk); messages past it are dropped."""


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


def _lock_folder(path: Path) -> int | None:
    """An exclusive flock on a folder (its fd), or None when another writer holds it."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _os_reason(err: OSError) -> str:
    return f"[Errno {err.errno}] {err.strerror}" if err.errno and err.strerror else str(err)


class SessionWriter:
    """Appends messages of named topics to a new Zarr v3 session store; thread-safe `append`."""

    def __init__(self, path: Path, topics: dict[str, str], config: RecorderConfig | None = None) -> None:
        import zarr

        self.path = path
        self.config = config or RecorderConfig()
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._start = time.monotonic()
        path.mkdir(parents=True, exist_ok=True)
        fd = _lock_folder(path)
        if fd is None:
            raise FileExistsError(f"{path} is being written by another recorder")
        self._folder_fd: int | None = fd
        try:
            self._root = cast(
                Any,
                zarr.open_group(
                    str(path),
                    mode="w-",
                    zarr_format=3,
                    attributes={
                        "format": FORMAT,
                        "format_version": FORMAT_VERSION,
                        "created_at": datetime.now(UTC).isoformat(),
                        "start_unix_s": time.time(),
                        "topics": topics,
                    },
                ),
            )
        except BaseException:
            self._unlock()
            raise
        rows, chunk = self.config.chunk_rows, self.config.chunk_bytes
        for name, key in topics.items():
            group = self._root.create_group(name, attributes={"key": key, "rows": 0, "bytes": 0})
            for column, dtype in INDEX_COLUMNS:
                _create(group, column, dtype, rows)
            _create(group, "data", "uint8", chunk)
            if name == TELEMETRY:
                for column, dtype in TELEMETRY_COLUMNS:
                    _create(group, column, dtype, rows)
        episodes = self._root.create_group(EPISODES, attributes={"rows": 0})
        for column, dtype in EPISODE_COLUMNS:
            _create(episodes, column, dtype, rows)
        self._buffers: dict[str, _Buffer] = {name: _Buffer() for name in topics}
        self._episodes: list[tuple[float, int, float, int, str]] = []
        self._observation_rows = 0
        self._pending_bytes = 0  # payload bytes received and not yet written
        self._last_flush = time.monotonic()
        self.rejected = 0
        self.written = 0
        self.dropped = 0
        """Messages dropped because writes failed for longer than `max_pending_bytes` lasts."""
        self.write_errors = 0
        self._failing = False  # the last flush failed (one log line per run of failures)

    def _unlock(self) -> None:
        if self._folder_fd is not None:
            os.close(self._folder_fd)  # releases the flock
            self._folder_fd = None

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
            if self._pending_bytes + len(payload) > self.config.max_pending_bytes:
                self.dropped += 1
                return
            self._pending_bytes += len(payload)
            buffer = self._buffers[topic]
            buffer.t.append(at)
            buffer.payloads.append(bytes(payload))
            if topic == OBSERVATIONS:
                self._observation_rows += 1
            if event is not None:
                buffer.events.append(event)
                if event.key.rsplit(".", 1)[-1] == EPISODE_END_NAME:
                    self._episodes.append((at, event.step, event.value, self._observation_rows, event.run_id))
            due = len(buffer.t) >= self.config.flush_rows and not self._failing  # else by the interval
        if due:
            self.flush()

    def flush_if_due(self) -> None:
        if time.monotonic() - self._last_flush >= self.config.flush_interval_s:
            self.flush()

    def flush(self) -> bool:
        """Write everything buffered, then commit the new row counts; True when all of it is written.

        What a failed write (OSError) held goes back in front of the buffers for the next flush."""
        failed: OSError | None = None
        with self._write_lock:  # taken before the swap: flushes write their rows in arrival order
            with self._lock:
                buffers, self._buffers = self._buffers, {name: _Buffer() for name in self._buffers}
                episodes, self._episodes = self._episodes, []
            for name, buffer in buffers.items():
                if not buffer.t:
                    continue
                try:
                    self._write_topic(name, buffer)
                except OSError as err:
                    failed = err
                    self._keep(name, buffer)
                else:
                    with self._lock:
                        self._pending_bytes -= sum(len(p) for p in buffer.payloads)
            if episodes:
                try:
                    self._write_episodes(episodes)
                except OSError as err:
                    failed = err
                    with self._lock:
                        self._episodes[:0] = episodes
            self._last_flush = time.monotonic()
            self._note(failed)
        return failed is None

    def _keep(self, name: str, buffer: _Buffer) -> None:
        """Put a buffer that was not written back in front of what arrived since."""
        with self._lock:
            newer = self._buffers[name]
            newer.t[:0], newer.payloads[:0], newer.events[:0] = buffer.t, buffer.payloads, buffer.events

    def _note(self, failed: OSError | None) -> None:
        """Count a failed flush; log the first of a run of failures and the flush that ends it."""
        if failed is not None:
            self.write_errors += 1
            WRITE_ERRORS.labels("recording").inc()
            if not self._failing:
                log.error(
                    "recording %s: messages not written: %s; they stay in memory (up to %d bytes) and "
                    "every flush tries again",
                    self.path,
                    _os_reason(failed),
                    self.config.max_pending_bytes,
                )
        elif self._failing:
            log.warning(
                "recording %s: writes go on; %d message(s) were dropped meanwhile", self.path, self.dropped
            )
        self._failing = failed is not None

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
        """Write what is buffered and, when all of it is written, mark the store closed (with the count of
        messages dropped while writes failed); releases the folder. A store left unmarked is cut back to
        its committed rows by the next `recover_recordings`."""
        try:
            if self.flush():
                closed = {"closed_at": datetime.now(UTC).isoformat(), "dropped": self.dropped}
                self._root.update_attributes(closed)
        except OSError as err:
            WRITE_ERRORS.labels("recording").inc()
            log.error("recording %s: not marked closed: %s", self.path, _os_reason(err))
        finally:
            self._unlock()


def _trim_and_append(array: Any, committed: int, values: np.ndarray) -> None:
    """Append after the committed length (rows past it, from an interrupted flush, are overwritten)."""
    if array.shape[0] != committed:
        array.resize((committed,))
    _append(array, values)


def _read_json(path: Path) -> dict[str, Any]:
    data = json.loads(path.read_bytes())
    if not isinstance(data, dict):
        raise ValueError(f"{path.name} is not a JSON object")
    return data


def _committed(path: Path) -> dict[str, int] | None:
    """A store's committed rows per group (None when it is not a Navi recording or is closed); raises
    ValueError or OSError when its metadata does not read."""
    attrs = _read_json(path / "zarr.json").get("attributes", {})
    if attrs.get("format") != FORMAT or "closed_at" in attrs:
        return None
    rows = {}
    for name in (*attrs["topics"], EPISODES):
        group = _read_json(path / name / "zarr.json").get("attributes", {})
        rows[name] = int(group["rows"])
        columns = [c for c, _ in INDEX_COLUMNS] + ["data"] if name != EPISODES else []
        columns += [c for c, _ in TELEMETRY_COLUMNS] if name == TELEMETRY else []
        columns += [c for c, _ in EPISODE_COLUMNS] if name == EPISODES else []
        for column in columns:
            _read_json(path / name / column / "zarr.json")
    return rows


def recover_recordings(folder: Path) -> list[str]:
    """Check the recording stores (*.zarr) in a folder that no writer holds: one not marked closed is cut
    back to its committed rows (partial chunk files of zarr's interrupted writes removed, arrays trimmed)
    and marked closed; one whose metadata does not read is renamed to `<name>.corrupt-<UTC time>`.
    Returns one line per store it changed (empty when every store was closed)."""
    import zarr

    done: list[str] = []
    if not folder.is_dir():
        return done
    for path in sorted(p for p in folder.iterdir() if p.suffix == ".zarr" and p.is_dir()):
        if not (path / "zarr.json").is_file():
            continue  # not a Zarr v3 store
        fd = _lock_folder(path)
        if fd is None:
            continue  # a live recorder writes it
        try:
            try:
                rows = _committed(path)
            except (OSError, ValueError, KeyError, TypeError) as err:
                stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
                aside = path.with_name(f"{path.name}.corrupt-{stamp}")
                os.rename(path, aside)
                done.append(f"recording {path} is unreadable ({err!r}): moved to {aside.name}")
                continue
            if rows is None:
                continue
            partials = sorted(path.rglob("*.partial"))
            for partial in partials:
                partial.unlink()
            root = cast(Any, zarr.open_group(str(path), mode="r+", zarr_format=3))
            cut = 0
            for name, committed in rows.items():
                group = root[name]
                ends = {column: committed for column in group.array_keys()}
                if name != EPISODES:
                    ends["data"] = int(group.attrs["bytes"])
                for column, end in ends.items():
                    if group[column].shape[0] > end:
                        cut += 1
                        group[column].resize((end,))
            root.update_attributes({"closed_at": datetime.now(UTC).isoformat()})
            kept = ", ".join(f"{n} {r}" for n, r in rows.items())
            done.append(
                f"recording {path} was not closed by its recorder: kept its committed rows ({kept}), "
                f"removed {len(partials)} partial chunk file(s), trimmed {cut} array(s), marked closed"
            )
        finally:
            os.close(fd)
    return done


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

    `on_ready` is called once the subscribers are declared (messages from then on are recorded). The
    stores next to `out` are checked first (`recover_recordings`), one log line for each it repairs.
    """
    for line in recover_recordings(out.parent):
        log.warning(line)
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
