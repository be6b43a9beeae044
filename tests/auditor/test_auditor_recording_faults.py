"""Recordings on a full disk and after a killed recorder: failed flushes are counted and written later,
a half-written store found at start is cut back to its committed rows (or moved aside when its metadata
does not read), and new recordings go on."""

from __future__ import annotations

import errno
import json
import logging
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest

from navi_auditor.recorder import RecorderConfig, SessionWriter, record, recover_recordings
from navi_auditor.replay import SessionReader
from navi_contracts.codec import encode
from navi_contracts.models import TelemetryEvent
from navi_mesh.metrics import REGISTRY

TOPICS = {"telemetry": "navi/telemetry"}


def event(i: int) -> bytes:
    return encode(
        TelemetryEvent(key="actor.training.sps", value=float(i), step=i, run_id="r1", timestamp=1.0)
    )


def assert_rows(path: Path, rows: int) -> None:
    """A reader sees exactly rows 0..rows-1, in order, with their values."""
    reader = SessionReader(path)
    assert reader.rows("telemetry") == rows
    _, values, steps = reader.telemetry()
    np.testing.assert_array_equal(steps, np.arange(rows))
    np.testing.assert_array_equal(values, np.arange(rows, dtype=np.float64))
    assert len(reader.payloads("telemetry")) == rows


def root_attrs(path: Path) -> dict[str, Any]:
    attrs: dict[str, Any] = json.loads((path / "zarr.json").read_text())["attributes"]
    return attrs


def write_errors() -> float:
    return REGISTRY.get_sample_value("navi_write_errors_total", {"what": "recording"}) or 0.0


def test_flushes_on_a_full_disk_are_counted_and_written_once_space_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from zarr.storage import LocalStore

    full = {"on": False}
    original = LocalStore.set

    async def set_or_enospc(self: LocalStore, key: str, value: Any) -> None:
        if full["on"]:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        await original(self, key, value)

    monkeypatch.setattr(LocalStore, "set", set_or_enospc)
    path = tmp_path / "s.zarr"
    writer = SessionWriter(
        path, TOPICS, RecorderConfig(flush_rows=10, chunk_rows=16, max_pending_bytes=10_000)
    )
    for i in range(20):
        writer.append("telemetry", event(i))
    before = write_errors()
    full["on"] = True
    with caplog.at_level(logging.WARNING, logger="navi_auditor.recorder"):
        for i in range(20, 60):
            writer.append("telemetry", event(i))  # no flush per append while writes fail
        assert not writer.flush() and not writer.flush()
        assert_rows(path, 20)
        assert write_errors() - before == 3 and writer.write_errors == 3
        full["on"] = False
        assert writer.flush()
    assert_rows(path, 60)
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2
    assert messages[0].startswith(
        f"recording {path}: messages not written: [Errno 28] No space left on device"
    )
    assert messages[1] == f"recording {path}: writes go on; 0 message(s) were dropped meanwhile"

    # Past max_pending_bytes, new messages are dropped and counted; the held ones are written in order.
    full["on"] = True
    sent = 60
    while writer.dropped == 0:
        writer.append("telemetry", event(sent))
        sent += 1
    full["on"] = False
    writer.close()
    assert_rows(path, sent - 1)
    assert root_attrs(path)["dropped"] == 1 and "closed_at" in root_attrs(path)


KILLED_SCRIPT = r"""
import os, re, signal, sys
from pathlib import Path
from navi_auditor.recorder import RecorderConfig, SessionWriter
from navi_contracts.codec import encode
from navi_contracts.models import TelemetryEvent
w = SessionWriter(Path(sys.argv[1]), {"telemetry": "navi/telemetry"},
                  RecorderConfig(flush_rows=10**9, chunk_rows=16, chunk_bytes=512))
def send(i):
    w.append("telemetry", encode(TelemetryEvent(key="actor.training.sps", value=float(i), step=i,
                                                run_id="r1", timestamp=1.0)))
for i in range(50):
    send(i)
w.flush()
def kill_mid_flush(event, args):
    # the second flush has written its key chunks and resized every column; its value chunk is written
    # to a .partial file and not yet renamed into place, and the row count is not yet committed
    if event == "os.rename" and re.search(r"/telemetry/value/c/[^/]*\.partial$", str(args[0])):
        os.kill(os.getpid(), signal.SIGKILL)
sys.addaudithook(kill_mid_flush)
for i in range(50, 90):
    send(i)
w.flush()
"""


def killed_recording(path: Path) -> None:
    """A store whose recorder was killed (SIGKILL) inside its second flush: 50 committed rows."""
    proc = subprocess.run([sys.executable, "-c", KILLED_SCRIPT, str(path)], timeout=120)
    assert proc.returncode == -9
    assert list(path.rglob("*.partial"))


class FakeZenoh:
    """Delivers messages to the subscribers `record` declares, when the test calls `publish`."""

    def __init__(self) -> None:
        self.handlers: list[tuple[str, Any]] = []

    def declare_subscriber(self, key: str, handler: Any) -> Any:
        self.handlers.append((key, handler))
        return self

    def undeclare(self) -> None:
        pass

    def publish(self, key: str, payload: bytes) -> None:
        for k, handler in self.handlers:
            if k == key:
                handler(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload)))


def test_a_killed_recording_is_cut_to_its_committed_rows_at_start_and_new_recordings_go_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    killed = tmp_path / "killed.zarr"
    killed_recording(killed)
    assert_rows(killed, 50)  # readers already skip the cut flush
    assert "closed_at" not in root_attrs(killed)
    zenoh = FakeZenoh()

    def ready() -> None:
        for i in range(5):
            zenoh.publish("navi/telemetry", event(i))

    with caplog.at_level(logging.WARNING, logger="navi_auditor.recorder"):
        writer = record(tmp_path / "new.zarr", TOPICS, 0.0, zenoh, on_ready=ready)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith(f"recording {killed} was not closed by its recorder")
    assert "telemetry 50" in lines[0]
    assert not list(killed.rglob("*.partial"))
    import zarr

    group = cast(Any, zarr.open_group(str(killed / "telemetry"), mode="r", zarr_format=3))
    columns = ("t", "offset", "length", "key", "value", "step")
    assert {name: group[name].shape[0] for name in columns} == dict.fromkeys(columns, 50)  # trimmed
    assert group["data"].shape[0] == group.attrs["bytes"]
    assert_rows(killed, 50)
    assert "closed_at" in root_attrs(killed)
    assert writer.written == 5 and "closed_at" in root_attrs(tmp_path / "new.zarr")
    assert_rows(tmp_path / "new.zarr", 5)
    assert recover_recordings(tmp_path) == []  # each store is checked once


def test_a_recording_whose_metadata_does_not_read_is_moved_aside(tmp_path: Path) -> None:
    path = tmp_path / "torn.zarr"
    writer = SessionWriter(path, TOPICS, RecorderConfig(flush_rows=10))
    for i in range(25):
        writer.append("telemetry", event(i))
    writer._unlock()  # the recorder dies here; the kernel releases its flock
    meta = path / "telemetry" / "zarr.json"
    raw = meta.read_bytes()
    meta.write_bytes(raw[: len(raw) // 2])
    done = recover_recordings(tmp_path)
    assert len(done) == 1 and done[0].startswith(f"recording {path} is unreadable (")
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("torn.zarr.corrupt-")]
    assert len(aside) == 1 and aside[0].name in done[0] and not path.exists()
    assert (aside[0] / "telemetry" / "zarr.json").read_bytes() == raw[: len(raw) // 2]  # kept as it was
    SessionWriter(path, TOPICS).close()  # the name is free for a new recording
    assert recover_recordings(tmp_path) == []


def test_a_store_a_live_recorder_writes_and_a_closed_store_are_left_alone(tmp_path: Path) -> None:
    live = SessionWriter(tmp_path / "live.zarr", TOPICS, RecorderConfig(flush_rows=10))
    done = SessionWriter(tmp_path / "done.zarr", TOPICS)
    done.append("telemetry", event(0))
    done.close()
    for i in range(25):
        live.append("telemetry", event(i))
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")}
    assert recover_recordings(tmp_path) == []
    assert {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*")} == before
    with pytest.raises(FileExistsError, match="another recorder"):
        SessionWriter(tmp_path / "live.zarr", TOPICS)
    live.close()
    assert_rows(tmp_path / "live.zarr", 25)
