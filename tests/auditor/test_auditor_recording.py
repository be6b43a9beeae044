"""Recording to Zarr v3 and replay: round trip, timing, and a recorder killed with SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

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


def test_replay_keeps_relative_timing(tmp_path: Path) -> None:
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
        arrivals: list[tuple[float, str]] = []

        def publish(key: str, payload: bytes, into: list[tuple[float, str]] = arrivals) -> None:
            into.append((time.monotonic(), key))

        stats = replay(entries, publish, rate=rate)
        assert stats.messages == 30
        got = np.array([a[0] for a in arrivals]) - arrivals[0][0]  # (T,)
        want = (times - times[0]) / rate  # (T,)
        assert np.max(np.abs(got - want)) < 0.03, np.max(np.abs(got - want))
        assert [a[1] for a in arrivals] == [
            TOPICS["observations" if i % 2 else "telemetry"] for i in range(30)
        ]


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


WRITER_SCRIPT = """
import sys, time
from pathlib import Path
from navi_auditor.recorder import RecorderConfig, SessionWriter
from navi_contracts.codec import encode
from navi_contracts.models import TelemetryEvent
w = SessionWriter(Path(sys.argv[1]), {"telemetry": "navi/telemetry"},
                  RecorderConfig(flush_interval_s=0.05, flush_rows=10**9, chunk_rows=64, chunk_bytes=2048))
i = 0
while True:
    w.append("telemetry", encode(TelemetryEvent(key="actor.training.sps", value=float(i), step=i, timestamp=1.0)))
    w.flush_if_due()
    i += 1
    time.sleep(0.001)
"""


def test_killed_recorder_leaves_a_readable_store(tmp_path: Path) -> None:
    path = tmp_path / "killed.zarr"
    proc = subprocess.Popen([sys.executable, "-c", WRITER_SCRIPT, str(path)])
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            time.sleep(0.2)
            try:
                if SessionReader(path).rows("telemetry") >= 200:
                    break
            except (SessionFormatError, KeyError, FileNotFoundError):
                continue
        time.sleep(0.137)  # land the kill somewhere inside the flush cycle
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    reader = SessionReader(path)
    rows = reader.rows("telemetry")
    assert rows >= 200
    _, values, steps = reader.telemetry()
    np.testing.assert_array_equal(steps, np.arange(rows))
    np.testing.assert_array_equal(values, np.arange(rows, dtype=np.float64))
    assert all(decode(p, TelemetryEvent).step == i for i, p in enumerate(reader.payloads("telemetry")))
    assert np.all(np.diff(reader.times("telemetry")) >= 0)
