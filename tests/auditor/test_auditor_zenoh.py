"""The auditor over a real Zenoh router on loopback: the passive feed, `navi record`, `navi replay`."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from fastapi.testclient import TestClient
from services_testlib import ReservedPort, client_session, matched, wait_for

from navi_auditor.replay import SessionFormatError, SessionReader, schedule
from navi_auditor.server import AuditorConfig, build_live_app
from navi_contracts.codec import decode, encode
from navi_contracts.models import DistanceMatrix, TelemetryEvent
from navi_contracts.settings import NaviSettings
from navi_contracts.topics import OBSERVATIONS, TELEMETRY

pytestmark = pytest.mark.integration


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


def test_dashboard_feed_is_passive_and_survives_garbage(
    zenoh_router: NaviSettings, zenoh_client: Any
) -> None:
    app, _ = build_live_app(zenoh_router, AuditorConfig())
    sent = 0
    block = zenoh.CongestionControl.BLOCK  # every message arrives: the counts below are exact
    with TestClient(app) as client:
        assert client.get("/api/state").json()["mode"] == "WAITING"
        for topic in (TELEMETRY, OBSERVATIONS):  # the feed's subscribers are the only ones yet
            matched(zenoh_client, topic.key)
        seen: list[str] = []
        spy = zenoh_client.declare_subscriber("navi/**", lambda s: seen.append(str(s.key_expr)))
        with client_session(zenoh_router.zenoh_connect) as probe:
            matched(probe, "navi/spy")  # the router knows of the spy: anything the dashboard sends reaches it
        for step in range(20):
            zenoh_client.put(TELEMETRY.key, encode(sps(step)), congestion_control=block)
            zenoh_client.put(OBSERVATIONS.key, encode(observation(step)), congestion_control=block)
            sent += 2
        for garbage in (b"", b"\xc1", encode(sps(0))[:-3], encode(observation(0))):
            zenoh_client.put(TELEMETRY.key, garbage, congestion_control=block)  # the last: valid, wrong type
            sent += 1
        zenoh_client.put(OBSERVATIONS.key, b"\x00" * 64, congestion_control=block)
        sent += 1
        wait_for(
            lambda: (
                client.get("/api/state").json()["decode_errors"] >= 5
                and client.get("/api/state").json()["frames"] >= 20
            ),
            60.0,
            "every message at the dashboard",
        )
        state = client.get("/api/state").json()
        assert state["mode"] == "TRAINING" and state["frames"] == 20 and state["sps"] == 119.0
        assert (state["decode_errors"], state["bad_frames"]) == (
            5,
            0,
        )  # every garbage payload, on both topics
        metrics = client.get("/metrics").text
        assert 'navi_decode_errors_total{topic="navi/telemetry"}' in metrics
        wait_for(lambda: len(seen) >= sent, 60.0, "the spy to hear this test's own traffic")
    spy.undeclare()
    # nothing on navi/** but our own traffic: the dashboard published nothing
    assert len(seen) == sent and set(seen) == {TELEMETRY.key, OBSERVATIONS.key}


def test_record_then_replay_over_zenoh(tmp_path: Path, zenoh_router: NaviSettings, zenoh_client: Any) -> None:
    out = tmp_path / "session.zarr"
    env = {**os.environ, "NAVI_ZENOH_CONNECT": zenoh_router.zenoh_connect}
    recorder = subprocess.Popen(
        [sys.executable, "-m", "navi", "record", "--out", str(out), "--topics", "telemetry", "--topics",
         "observations", "--json"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    sent: list[tuple[str, bytes]] = []
    try:
        assert recorder.stderr is not None
        lines = [recorder.stderr.readline()]
        while "recording" not in lines[-1] and len(lines) < 20:  # printed once the subscribers are declared
            lines.append(recorder.stderr.readline())
        assert "recording" in lines[-1], lines
        for topic in (TELEMETRY, OBSERVATIONS):  # the recorder's subscribers are the only ones
            matched(zenoh_client, topic.key)
        for step in range(12):
            key = TELEMETRY.key if step % 2 else OBSERVATIONS.key
            sent.append((key, encode(sps(step) if step % 2 else observation(step))))
            zenoh_client.put(*sent[-1], congestion_control=zenoh.CongestionControl.BLOCK)

        def recorded() -> int:
            """Rows the recorder has flushed so far (it flushes every second)."""
            try:
                reader = SessionReader(out)
                return reader.rows("telemetry") + reader.rows("observations")
            except (SessionFormatError, KeyError, FileNotFoundError):
                return 0

        wait_for(lambda: recorded() == 12, 60.0, "all 12 messages in the store")
    finally:
        recorder.send_signal(signal.SIGINT)
        stdout, stderr = recorder.communicate(timeout=120)
    assert recorder.returncode == 0, stderr
    assert json.loads(stdout)["messages"] == 12
    reader = SessionReader(out)
    assert reader.rows("telemetry") == 6 and reader.rows("observations") == 6
    assert reader.payloads("telemetry") == [p for k, p in sent if k == TELEMETRY.key]
    assert reader.payloads("observations") == [p for k, p in sent if k == OBSERVATIONS.key]

    # `navi replay` republishes the session in its recorded order (its timing: test_auditor_recording).
    heard: list[tuple[str, bytes]] = []
    with client_session(zenoh_router.zenoh_connect) as listener:
        sub = listener.declare_subscriber(
            "navi/**", lambda s: heard.append((str(s.key_expr), s.payload.to_bytes()))
        )
        for topic in (TELEMETRY, OBSERVATIONS):
            matched(zenoh_client, topic.key)  # the listener is known to the router before the replay
        replayer = subprocess.run(
            [sys.executable, "-m", "navi", "replay", str(out), "--rate", "2.0", "--json"],
            env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert replayer.returncode == 0, replayer.stderr
        assert json.loads(replayer.stdout)["messages"] == 12
        wait_for(lambda: len(heard) >= 12, 60.0, "the replayed messages")
        sub.undeclare()
    assert heard == [(key, payload) for _, key, payload in schedule(reader)]  # the recorded order
    assert sorted(heard) == sorted(sent)
    for key, payload in heard:
        decode(payload, TelemetryEvent if key == TELEMETRY.key else DistanceMatrix)


def open_router(port: int) -> Any:
    from navi_mesh.session import SessionConfig, open_new_session

    return open_new_session(SessionConfig(mode="router", connect=(), listen=(f"tcp/127.0.0.1:{port}",)))


def publish_until(settings: NaviSettings, client: TestClient, step: int) -> None:
    """Publish an SPS sample every 0.2 s until the dashboard shows it (the feed may still be reconnecting)."""
    with client_session(settings.zenoh_connect) as session:

        def shown() -> bool:
            session.put(TELEMETRY.key, encode(sps(step)))
            return bool(client.get("/api/state").json()["sps"] == 100.0 + step)

        wait_for(shown, 120.0, f"the dashboard to show sample {step}", poll_s=0.2)


def test_dashboard_starts_before_the_router_and_survives_its_restart(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="navi.auditor.feed")
    with ReservedPort() as reserved:  # where the router will listen, and listen again after its restart
        settings = NaviSettings(zenoh_connect=f"tcp/127.0.0.1:{reserved.port}")
        app, _ = build_live_app(settings, AuditorConfig())
        with TestClient(app) as client:
            wait_for(
                lambda: any("no Zenoh router yet" in r.getMessage() for r in caplog.records),
                120.0,
                "the feed to try while there is no router",
            )
            assert client.get("/api/state").json()["mode"] == "WAITING"
            router = open_router(reserved.port)
            try:
                publish_until(settings, client, 1)
            finally:
                router.close()
            router = open_router(reserved.port)  # a restarted router: the feed's session reconnects by itself
            try:
                publish_until(settings, client, 2)
                assert client.get("/api/state").json()["mode"] == "TRAINING"
            finally:
                router.close()
