"""The auditor over a real Zenoh router on loopback: the passive feed, `navi record`, `navi replay`."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from navi_auditor.replay import SessionReader
from navi_auditor.server import AuditorConfig, build_live_app
from navi_contracts.codec import decode, encode
from navi_contracts.models import DistanceMatrix, TelemetryEvent
from navi_contracts.settings import NaviSettings
from navi_contracts.topics import OBSERVATIONS, TELEMETRY

pytestmark = pytest.mark.integration


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def observation(step: int) -> DistanceMatrix:
    depth = np.full((1, 16, 4), 0.25, np.float32)  # (N, Az, El)
    return DistanceMatrix(
        env_ids=np.zeros(1, np.int32),
        azimuth_bins=16,
        elevation_bins=4,
        depth=depth,
        semantic=depth,
        delta_depth=depth * 0,
        step_id=step,
        timestamp=time.time(),
        run_id="z",
    )


def sps(step: int) -> TelemetryEvent:
    return TelemetryEvent(
        key="actor.training.sps", value=100.0 + step, step=step, run_id="z", timestamp=time.time()
    )


def wait_for(predicate: Any, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.05)


def test_dashboard_feed_is_passive_and_survives_garbage(
    zenoh_router: NaviSettings, zenoh_client: Any
) -> None:
    seen: list[str] = []
    spy = zenoh_client.declare_subscriber("navi/**", lambda s: seen.append(str(s.key_expr)))
    app, _ = build_live_app(zenoh_router, AuditorConfig())
    sent = 0
    with TestClient(app) as client:
        assert client.get("/api/state").json()["mode"] == "WAITING"
        time.sleep(1.0)  # let the feed connect and declare its subscribers
        for step in range(20):
            zenoh_client.put(TELEMETRY.key, encode(sps(step)))
            zenoh_client.put(OBSERVATIONS.key, encode(observation(step)))
            sent += 2
            time.sleep(0.02)
        for garbage in (b"", b"\xc1", encode(sps(0))[:-3], encode(observation(0))):
            zenoh_client.put(TELEMETRY.key, garbage)  # the last one is a valid message of the wrong type
            sent += 1
        zenoh_client.put(OBSERVATIONS.key, b"\x00" * 64)
        sent += 1
        wait_for(lambda: client.get("/api/state").json()["decode_errors"] >= 5)
        state = client.get("/api/state").json()
        assert state["mode"] == "TRAINING" and state["frames"] == 20 and state["sps"] == 119.0
        assert (state["decode_errors"], state["bad_frames"]) == (
            5,
            0,
        )  # every garbage payload, on both topics
        metrics = client.get("/metrics").text
        assert 'navi_decode_errors_total{topic="navi/telemetry"}' in metrics
        time.sleep(0.3)
    spy.undeclare()
    assert len(seen) == sent  # nothing on navi/** but our own traffic: the dashboard published nothing


def test_record_then_replay_over_zenoh(tmp_path: Path, zenoh_router: NaviSettings, zenoh_client: Any) -> None:
    out = tmp_path / "session.zarr"
    env = {**os.environ, "NAVI_ZENOH_CONNECT": zenoh_router.zenoh_connect}
    recorder = subprocess.Popen(
        [sys.executable, "-m", "navi", "record", "--out", str(out), "--topics", "telemetry", "--topics",
         "observations", "--json"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert recorder.stderr is not None
        lines = [recorder.stderr.readline()]
        while "recording" not in lines[-1] and len(lines) < 20:  # printed once the subscribers are declared
            lines.append(recorder.stderr.readline())
        assert "recording" in lines[-1], lines
        time.sleep(0.3)
        gaps = [0.05, 0.2, 0.1, 0.3, 0.05, 0.15]
        for step, gap in enumerate(gaps * 2):
            zenoh_client.put(TELEMETRY.key if step % 2 else OBSERVATIONS.key,
                             encode(sps(step) if step % 2 else observation(step)))  # fmt: skip
            time.sleep(gap)
        time.sleep(0.5)
    finally:
        recorder.send_signal(signal.SIGINT)
        stdout, stderr = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, stderr
    assert '"messages": 12' in stdout
    reader = SessionReader(out)
    assert reader.rows("telemetry") == 6 and reader.rows("observations") == 6
    recorded = np.sort(np.concatenate([reader.times("telemetry"), reader.times("observations")]))  # (T,)

    arrivals: list[float] = []
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        decode(
            sample.payload.to_bytes(),
            TelemetryEvent if "telemetry" in str(sample.key_expr) else DistanceMatrix,
        )
        with lock:
            arrivals.append(time.monotonic())

    listener = zenoh_client.declare_subscriber("navi/**", on_sample)
    time.sleep(0.5)
    replayer = subprocess.run(
        [sys.executable, "-m", "navi", "replay", str(out), "--rate", "2.0", "--json"],
        env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert replayer.returncode == 0, replayer.stderr
    wait_for(lambda: len(arrivals) == 12)
    listener.undeclare()
    got = np.array(arrivals) - arrivals[0]  # (T,)
    want = (recorded - recorded[0]) / 2.0  # (T,)
    assert np.max(np.abs(got - want)) < 0.08, (got, want)


def open_router(port: int) -> Any:
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def publish_until(settings: NaviSettings, client: TestClient, step: int) -> None:
    """Publish an SPS sample every 0.2 s until the dashboard shows it."""
    from navi_mesh.session import config_from_settings, open_new_session

    session = open_new_session(config_from_settings(settings, connect_timeout_s=10.0))
    try:
        deadline = time.monotonic() + 15.0
        while client.get("/api/state").json()["sps"] != 100.0 + step:
            assert time.monotonic() < deadline, "the dashboard never saw the sample"
            session.put(TELEMETRY.key, encode(sps(step)))
            time.sleep(0.2)
    finally:
        session.close()


def test_dashboard_starts_before_the_router_and_survives_its_restart() -> None:
    port = free_port()
    settings = NaviSettings(zenoh_connect=f"tcp/127.0.0.1:{port}")
    app, _ = build_live_app(settings, AuditorConfig())
    with TestClient(app) as client:
        time.sleep(1.5)  # the feed retries while there is no router
        assert client.get("/api/state").json()["mode"] == "WAITING"
        router = open_router(port)
        try:
            publish_until(settings, client, 1)
        finally:
            router.close()
        router = open_router(port)  # a restarted router: the feed's session reconnects by itself
        try:
            publish_until(settings, client, 2)
            assert client.get("/api/state").json()["mode"] == "TRAINING"
        finally:
            router.close()
