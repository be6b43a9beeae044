"""Recording to Zarr v3 and replay: round trip, timing, and a recorder killed with SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from services_testlib import wait_for

from navi_auditor.recorder import RecorderConfig, SessionWriter
from navi_auditor.replay import SessionFormatError, SessionReader, replay, schedule
from navi_contracts.codec import decode, encode
from navi_contracts.models import DistanceMatrix, TelemetryEvent

TOPICS = {"observations": "navi/env/observations", "telemetry": "navi/telemetry"}


def observation(step: int, az: int = 16, el: int = 4) -> DistanceMatrix:
    rng = np.random.default_rng(step)
    depth = rng.random((2, az, el), dtype=np.float32)  # (N, Az, El)
    return DistanceMatrix(
        env_ids=np.arange(2, dtype=np.int32),
        azimuth_bins=az,
        elevation_bins=el,
        depth=depth,
        semantic=np.zeros_like(depth),
        delta_depth=depth - 0.5,
        step_id=step,
        timestamp=1000.0 + step,
        run_id="r1",
    )


def telemetry(key: str, value: float, step: int) -> TelemetryEvent:
    return TelemetryEvent(key=key, value=value, step=step, run_id="r1", timestamp=2000.0 + step)


def test_session_round_trips_messages_columns_and_episodes(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    writer = SessionWriter(path, TOPICS, RecorderConfig(flush_rows=7, chunk_rows=16, chunk_bytes=4096))
    sent_obs, sent_tel = [], []
    for i in range(40):
        sent_obs.append(observation(i))
        writer.append("observations", encode(sent_obs[-1]), t=0.1 * i)
        key = "actor.training.episode_return" if i % 10 == 9 else "actor.training.sps"
        sent_tel.append(telemetry(key, float(i), i))
        writer.append("telemetry", encode(sent_tel[-1]), t=0.1 * i + 0.05)
    writer.append("telemetry", b"\x93garbage", t=5.0)
    writer.close()

    reader = SessionReader(path)
    assert reader.rows("observations") == 40 and reader.rows("telemetry") == 40
    assert writer.rejected == 1
    np.testing.assert_allclose(reader.times("observations"), 0.1 * np.arange(40))
    for got, want in zip(reader.payloads("observations"), sent_obs, strict=True):
        back = decode(got, DistanceMatrix)
        assert back.step_id == want.step_id
        np.testing.assert_array_equal(back.depth, want.depth)
        np.testing.assert_array_equal(back.delta_depth, want.delta_depth)
    keys, values, steps = reader.telemetry()
    assert list(keys) == [e.key for e in sent_tel]
    np.testing.assert_array_equal(values, [e.value for e in sent_tel])
    np.testing.assert_array_equal(steps, np.arange(40))
    episodes = reader.episodes()
    np.testing.assert_array_equal(episodes["step"], [9, 19, 29, 39])
    np.testing.assert_array_equal(episodes["row"], [10, 20, 30, 40])  # observation rows before each end
    assert list(episodes["run_id"]) == ["r1"] * 4


def test_reader_rejects_a_foreign_store(tmp_path: Path) -> None:
    import zarr

    zarr.open_group(str(tmp_path / "x.zarr"), mode="w", zarr_format=3)
    with pytest.raises(SessionFormatError):
        SessionReader(tmp_path / "x.zarr")
    with pytest.raises(SessionFormatError):
        SessionReader(tmp_path / "missing.zarr")


class Clock(threading.Event):
    """The replay's clock, set by the test: `time` of navi_auditor.replay reads `now`, and waiting on this
    event (the replay's stop event) moves `now` on by the time waited, at once."""

    def __init__(self) -> None:
        super().__init__()
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    def wait(self, timeout: float | None = None) -> bool:
        self.now += timeout or 0.0
        return False

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


def test_replay_keeps_relative_timing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import navi_auditor.replay as replay_module

    path = tmp_path / "s.zarr"
    writer = SessionWriter(path, TOPICS)
    times = np.cumsum(np.random.default_rng(0).uniform(0.0, 0.08, size=30))  # (T,) irregular gaps
    for i, t in enumerate(times):
        topic = "observations" if i % 2 else "telemetry"
        message = observation(i) if i % 2 else telemetry("actor.training.sps", 1.0, i)
        writer.append(topic, encode(message), t=float(t))
    writer.close()
    entries = schedule(SessionReader(path))
    assert [e[0] for e in entries] == sorted(e[0] for e in entries)

    for rate in (1.0, 2.0):
        clock = Clock()
        monkeypatch.setattr(replay_module, "time", clock)
        arrivals: list[tuple[float, str]] = []

        def publish(
            key: str, payload: bytes, into: list[tuple[float, str]] = arrivals, c: Clock = clock
        ) -> None:
            into.append((c.now, key))

        stats = replay(entries, publish, rate=rate, stop=clock)
        assert stats.messages == 30 and stats.max_lag_s == pytest.approx(0.0, abs=1e-9)
        got = np.array([a[0] for a in arrivals])  # (T,) seconds after the start
        np.testing.assert_allclose(got, (times - times[0]) / rate, rtol=0, atol=1e-9)
        assert [a[1] for a in arrivals] == [
            TOPICS["observations" if i % 2 else "telemetry"] for i in range(30)
        ]

    # A publish that takes 0.5 s delays what was due meanwhile, never what comes after: the schedule
    # stays anchored at the start, and the lag is reported.
    clock = Clock()
    monkeypatch.setattr(replay_module, "time", clock)
    stalled: list[float] = []

    def slow_tenth(key: str, payload: bytes) -> None:
        stalled.append(clock.now)
        if len(stalled) == 10:
            clock.now += 0.5

    stats = replay(entries, slow_tenth, rate=1.0, stop=clock)
    due = times - times[0]  # (T,)
    np.testing.assert_allclose(
        stalled, np.maximum(due, np.where(np.arange(30) > 9, due[9] + 0.5, 0.0)), atol=1e-9
    )
    assert stats.max_lag_s == pytest.approx(0.5, abs=1e-9)


def test_every_committed_state_a_kill_can_leave_is_consistent(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each version of a topic's metadata the store ever holds (a kill can leave any one of them) has
    `bytes` equal to the end of its last committed payload: the two counts are written together."""
    import json

    from zarr.core.buffer import Buffer
    from zarr.storage import LocalStore

    versions: list[dict[str, int]] = []
    original = LocalStore.set

    async def recording_set(self: LocalStore, key: str, value: Buffer) -> None:
        await original(self, key, value)
        attrs = json.loads(value.to_bytes())["attributes"] if key == "telemetry/zarr.json" else {}
        if "rows" in attrs:  # (the group is created before its counts; readers skip it until then)
            versions.append({"rows": int(attrs["rows"]), "bytes": int(attrs.get("bytes", -1))})

    monkeypatch.setattr(LocalStore, "set", recording_set)
    path = tmp_path / "s.zarr"
    writer = SessionWriter(path, {"telemetry": "navi/telemetry"}, RecorderConfig(flush_rows=7, chunk_rows=16))
    for i in range(60):
        writer.append("telemetry", encode(telemetry("actor.training.sps", float(i), i)))
    writer.close()
    reader = SessionReader(path)
    ends = np.concatenate([[0], np.cumsum(reader.column("telemetry", "length"))])  # (T + 1,) bytes
    assert len(versions) >= 60 // 7 and versions[-1]["rows"] == 60
    for v in versions:
        assert v["bytes"] == ends[v["rows"]], v


WRITER_SCRIPT = r"""
import os, re, sys, threading, time
from pathlib import Path
from navi_auditor.recorder import RecorderConfig, SessionWriter
from navi_contracts.codec import encode
from navi_contracts.models import TelemetryEvent
w = SessionWriter(Path(sys.argv[1]), {"telemetry": "navi/telemetry"},
                  RecorderConfig(flush_interval_s=0.05, flush_rows=10**9, chunk_rows=64, chunk_bytes=2048))
armed = threading.Event()
def hold(event, args):
    # inside the first flush after 200 committed rows: this flush's key chunks are in place, its value
    # chunks not yet, the row count not yet; the writer stays there until it is killed
    if armed.is_set() and event == "os.rename" and re.search(r"/telemetry/value/c/[^/]*\.partial$", str(args[0])):
        armed.clear()
        Path(sys.argv[2]).write_text(str(os.getpid()))
        threading.Event().wait()
sys.addaudithook(hold)
i = 0
while True:
    w.append("telemetry", encode(TelemetryEvent(key="actor.training.sps", value=float(i), step=i, timestamp=1.0)))
    if i == 199:
        w.flush()
        armed.set()
    else:
        w.flush_if_due()
    i += 1
    time.sleep(0.001)
"""


def committed(path: Path) -> int:
    """Rows a reader sees, after checking every one against what the writer wrote."""
    reader = SessionReader(path)
    rows = reader.rows("telemetry")
    _, values, steps = reader.telemetry()
    np.testing.assert_array_equal(steps, np.arange(rows))
    np.testing.assert_array_equal(values, np.arange(rows, dtype=np.float64))
    assert all(decode(p, TelemetryEvent).step == i for i, p in enumerate(reader.payloads("telemetry")))
    assert np.all(np.diff(reader.times("telemetry")) >= 0)
    return rows


def test_killed_recorder_leaves_a_readable_store(tmp_path: Path) -> None:
    path, held = tmp_path / "killed.zarr", tmp_path / "held"
    proc = subprocess.Popen([sys.executable, "-c", WRITER_SCRIPT, str(path), str(held)])
    try:

        def holding() -> bool:
            assert proc.poll() is None, "the writer exited"
            return held.is_file() and held.read_text() == str(proc.pid)

        wait_for(holding, 300.0, "the writer to stop inside a flush")
        assert committed(path) == 200  # a reader during the half-done flush sees the last committed rows
    finally:
        os.kill(proc.pid, signal.SIGKILL)  # kill -9 inside that flush
        proc.wait(60)
    assert committed(path) == 200
    assert list(path.rglob("*.partial"))  # the flush was cut: a partial chunk write stays (readers skip it)
