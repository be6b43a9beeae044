"""`navi replay`: read a recorded Zarr session and republish it on Zenoh with the original timing.

`SessionReader` reads only committed rows (see recorder.py), so a store left by a killed recorder reads
cleanly. `replay` is a plain loop over (t, key, payload) that sleeps until each message's time divided by
`rate` and hands it to a publish function: Zenoh in `navi replay`, anything in tests.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from navi_auditor.recorder import EPISODES, FORMAT, TELEMETRY


class SessionFormatError(ValueError):
    """The path is not a readable Navi session store."""


class SessionReader:
    """Read access to a session store written by `SessionWriter` (committed rows only)."""

    def __init__(self, path: Path) -> None:
        import zarr

        try:
            self._root = cast(Any, zarr.open_group(str(path), mode="r", zarr_format=3))
        except (FileNotFoundError, ValueError, KeyError) as exc:
            raise SessionFormatError(f"{path} is not a Zarr v3 store: {exc}") from exc
        if self._root.attrs.get("format") != FORMAT:
            raise SessionFormatError(f"{path} is not a Navi session (format attribute is not {FORMAT!r})")
        self.path = path
        self.topics: dict[str, str] = dict(self._root.attrs["topics"])
        self.start_unix_s = float(self._root.attrs["start_unix_s"])

    def rows(self, topic: str) -> int:
        return int(self._root[topic].attrs["rows"])

    def column(self, topic: str, name: str) -> np.ndarray:
        """A committed per-message column of a topic (or of `episodes`): (T,)."""
        group = self._root[topic]
        return np.asarray(group[name][: int(group.attrs["rows"])])  # (T,)

    def times(self, topic: str) -> np.ndarray:
        return self.column(topic, "t")  # (T,) float64 seconds since the session start

    def payloads(self, topic: str) -> list[bytes]:
        """The raw messages of a topic, in arrival order."""
        group = self._root[topic]
        offsets, lengths = self.column(topic, "offset"), self.column(topic, "length")  # (T,), (T,)
        data = np.asarray(group["data"][: int(group.attrs["bytes"])]).tobytes()  # B bytes
        return [data[o : o + n] for o, n in zip(offsets.tolist(), lengths.tolist(), strict=True)]

    def telemetry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Decoded telemetry columns: key (T,) str, value (T,) float64, step (T,) int64."""
        return self.column(TELEMETRY, "key"), self.column(TELEMETRY, "value"), self.column(TELEMETRY, "step")

    def episodes(self) -> dict[str, np.ndarray]:
        """The episode index: t, step, value (return), row (observation rows before the end), run_id."""
        return {name: self.column(EPISODES, name) for name in ("t", "step", "value", "row", "run_id")}


def schedule(reader: SessionReader, topics: list[str] | None = None) -> list[tuple[float, str, bytes]]:
    """Every message of the chosen topics as (t, key, payload), in time order."""
    entries: list[tuple[float, str, bytes]] = []
    for name in topics or list(reader.topics):
        key = reader.topics[name]
        entries += [
            (t, key, p) for t, p in zip(reader.times(name).tolist(), reader.payloads(name), strict=True)
        ]
    entries.sort(key=lambda e: e[0])
    return entries


@dataclass(frozen=True)
class ReplayStats:
    messages: int
    wall_s: float
    max_lag_s: float  # worst lateness of a publish versus its scheduled time


def replay(
    entries: list[tuple[float, str, bytes]],
    publish: Callable[[str, bytes], None],
    rate: float = 1.0,
    stop: threading.Event | None = None,
) -> ReplayStats:
    """Publish each entry at (t - t_first) / rate seconds after the start; returns timing stats."""
    if rate <= 0:
        raise ValueError("rate must be positive")
    halt = stop or threading.Event()
    start = time.monotonic()
    t0 = entries[0][0] if entries else 0.0
    max_lag = 0.0
    sent = 0
    for t, key, payload in entries:
        due = start + (t - t0) / rate
        wait = due - time.monotonic()
        if wait > 0 and halt.wait(wait):
            break
        if halt.is_set():
            break
        publish(key, payload)
        max_lag = max(max_lag, time.monotonic() - due)
        sent += 1
    return ReplayStats(messages=sent, wall_s=time.monotonic() - start, max_lag_s=max_lag)


def zenoh_publisher(session: Any) -> Callable[[str, bytes], None]:
    """A publish function over declared Zenoh publishers (one per key, declared on first use)."""
    publishers: dict[str, Any] = {}

    def publish(key: str, payload: bytes) -> None:
        publisher = publishers.get(key)
        if publisher is None:
            publisher = publishers[key] = session.declare_publisher(key)
        publisher.put(payload)

    return publish
