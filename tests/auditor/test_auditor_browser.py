"""The live dashboard in a real headless Chromium, fed over a real Zenoh router on loopback.

The page must show WAITING first, then the corpus build, then frames, the right mode (TRAINING, then
INFERENCE) and every label equal to the value this test streamed (actors, SPS, observation age, run,
step, the newest point of each training chart, actor 0's pose, its trail over the floor plan).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from navi_auditor.dashboard import create_app
from navi_auditor.demos import load_demo
from navi_auditor.explorer import Explorer, ExplorerConfig, explorer_hub, explorer_routes
from navi_auditor.hub import Hub
from navi_auditor.server import AuditorConfig, BackgroundServer, build_live_app
from navi_auditor.state import DashboardState
from navi_contracts.codec import encode
from navi_contracts.models import DistanceMatrix, FloorPlan, RobotPose, TelemetryEvent
from navi_contracts.settings import NaviSettings
from navi_contracts.topics import FLOOR_PLAN, OBSERVATIONS, POSES, TELEMETRY

CHROMIUM = Path(shutil.which("chromium") or "/usr/bin/chromium")
"""Debian's chromium, found on PATH as `.ci/run` finds it."""
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SCREENSHOTS = Path(__file__).resolve().parents[2] / "artifacts" / "test-screenshots"
WAIT_MS = 120_000
"""Bounds a hang only: the page follows the stream within a frame or two."""

pytestmark = pytest.mark.integration


def corridor(az: int, el: int, step: int, stamp: float | None = None) -> DistanceMatrix:
    """A synthetic view: near walls to the left and right, open ahead and behind."""
    azimuth = np.arange(az, dtype=np.float32)[:, None] * (2 * np.pi / az)  # (Az, 1)
    elevation = np.linspace(-np.pi / 2, np.pi / 2, el, dtype=np.float32)[None, :]  # (1, El)
    side = np.abs(np.sin(azimuth)) + 0.05  # (Az, 1)
    depth = np.clip(0.08 / side / np.maximum(np.cos(elevation), 0.1), 0.0, 1.0)  # (Az, El)
    depth = np.broadcast_to(depth, (az, el)).astype(np.float32)[None]  # (1, Az, El)
    zeros = np.zeros_like(depth)  # (1, Az, El)
    return DistanceMatrix(
        env_ids=np.zeros(1, np.int32),
        azimuth_bins=az,
        elevation_bins=el,
        depth=depth,
        semantic=zeros,
        delta_depth=zeros,
        step_id=step,
        timestamp=time.time() if stamp is None else stamp,
        run_id="browser-test",
    )


def telemetry(key: str, value: float, step: int) -> bytes:
    return encode(
        TelemetryEvent(key=key, value=value, step=step, run_id="browser-test", timestamp=time.time())
    )


def browser_api() -> Any:
    """Playwright's sync API, or a skip naming what is missing (never downloads a browser)."""
    if not CHROMIUM.exists():
        pytest.skip(
            f"Debian's chromium is not installed (no chromium on PATH, none at {CHROMIUM}; apt-get install -y chromium)"
        )
    return pytest.importorskip("playwright.sync_api", reason="the playwright Python package is not installed")


def room_plan() -> FloorPlan:
    """A 16 m square room, 0.5 m cells: walls (clearance <= 0) on the outer ring, free inside."""
    centres = (np.arange(32, dtype=np.float32) + 0.5) * 0.5  # (32,) cell centres, meters
    gx, gy = np.meshgrid(centres, centres)  # (32, 32) each, row = y
    clearance = np.minimum(np.minimum(gx - 0.5, 15.5 - gx), np.minimum(gy - 0.5, 15.5 - gy))  # (32, 32)
    return FloorPlan(scene="room", run_id="browser-test", origin_x=0.0, origin_y=0.0, cell_size=0.5, z=4.0,
                     clearance=clearance.astype(np.float32), timestamp=time.time())  # fmt: skip


CHOSEN = {  # the values this test streams, and the label each must show on the page
    "collisions_per_1k": ("#last-collisions", 3.5, "3.5"),
    "coverage_per_1k": ("#last-coverage", 12.25, "12.25"),
    "episode_return": ("#last-episode_return", -4.5, "-4.5"),
    "entropy": ("#last-entropy", 1.75, "1.75"),
    "value_loss": ("#last-value_loss", 0.125, "0.125"),
    "reward_ema": ("#last-reward", 0.875, "0.875"),
    "sps": ("#last-sps", 1234.0, "1234"),
}


def pixel(page: Any, canvas: str, x: int, y: int) -> list[int]:
    rgba: list[int] = page.evaluate(
        f"Array.from(document.getElementById('{canvas}').getContext('2d').getImageData({x}, {y}, 1, 1).data)"
    )
    return rgba[:3]


def test_browser_shows_each_label_of_a_chosen_stream(zenoh_router: NaviSettings, zenoh_client: Any) -> None:
    import zenoh

    sync_api = browser_api()
    app, state = build_live_app(zenoh_router, AuditorConfig())
    server = BackgroundServer(app, port=0).start()  # the OS picks the port; url names it
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1400, "height": 1100})
            page.goto(server.url)
            page.wait_for_selector("#link.up", timeout=WAIT_MS)
            assert page.inner_text("#mode") == "WAITING"
            assert page.get_attribute("#heatmap", "data-seq") == "0"
            assert page.is_visible("#waiting") and not page.is_visible("#corpus")
            SCREENSHOTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SCREENSHOTS / "auditor_dashboard_waiting.png"))

            # The corpus is being built: OBSERVER (no actor telemetry yet) and its progress.
            for key, value in (("scenes_planned", 4.0), ("scenes_ready", 2.0), ("scenes_rejected", 1.0)):
                zenoh_client.put(TELEMETRY.key, telemetry(f"corpus.{key}", value, 0))
            zenoh_client.put(TELEMETRY.key, telemetry("corpus.ready", 0.0, 0))
            page.wait_for_function(
                "document.getElementById('corpus').textContent === 'Corpus=2/4 building, 1 scenes rejected'",
                timeout=WAIT_MS,
            )
            assert page.inner_text("#mode") == "OBSERVER"
            # Rejected scenes and undecodable messages are counted apart: a scene is not a message.
            assert page.inner_text("#decode-errors") == "Decode errors=0"
            zenoh_client.put(TELEMETRY.key, b"\xc1")  # not msgpack
            page.wait_for_function(
                "document.getElementById('decode-errors').textContent === 'Decode errors=1'", timeout=WAIT_MS
            )
            assert "1 scenes rejected" in page.inner_text("#corpus")
            assert page.inner_text("#bad-frames") == "Bad frames=0"
            zenoh_client.put(TELEMETRY.key, telemetry("corpus.scenes_rejected", 0.0, 0))
            zenoh_client.put(TELEMETRY.key, telemetry("corpus.scenes_ready", 4.0, 0))
            zenoh_client.put(TELEMETRY.key, telemetry("corpus.ready", 1.0, 0))
            page.wait_for_function(
                "document.getElementById('corpus').textContent === 'Corpus=4/4 ready'", timeout=WAIT_MS
            )

            zenoh_client.put(FLOOR_PLAN.key, encode(room_plan()))
            stamped = time.time() - 1.5  # every frame was taken 1.5 s before it is sent
            block = zenoh.CongestionControl.BLOCK  # every message arrives (the page counts frames and poses)
            for step in range(1, 41):
                zenoh_client.put(
                    OBSERVATIONS.key, encode(corridor(256, 48, step, stamped)), congestion_control=block
                )
                x = 2.0 + 8.0 * step / 40  # actor 0 flies from (2, 8) to (10, 8) at 4 m
                pose = RobotPose(env_id=0, x=x, y=8.0, z=4.0, roll=0, pitch=0, yaw=0, timestamp=stamped)
                zenoh_client.put(POSES.key, encode(pose), congestion_control=block)
                if step % 10 == 0:
                    for name, (_, value, _) in CHOSEN.items():
                        zenoh_client.put(
                            TELEMETRY.key,
                            telemetry(f"actor.training.{name}", value, step * 4),
                            congestion_control=block,
                        )
                    zenoh_client.put(
                        TELEMETRY.key,
                        telemetry("actor.training.actors", 4.0, step * 4),
                        congestion_control=block,
                    )
            page.wait_for_function(
                "document.getElementById('mode').textContent === 'TRAINING'", timeout=WAIT_MS
            )
            page.wait_for_function("document.getElementById('pose').textContent.startsWith('Pose=10.00')",
                                   timeout=WAIT_MS)  # fmt: skip
            page.wait_for_function(  # the 40th frame drawn: every frame reached the dashboard
                "Number(document.getElementById('heatmap').dataset.seq) === 40", timeout=WAIT_MS
            )
            assert page.inner_text("#actors") == "Actors=4"
            assert page.inner_text("#sps") == "SPS=1234"
            assert page.inner_text("#run") == "Run=browser-test"
            assert page.inner_text("#step") == "Step=160"
            assert page.inner_text("#bad-frames") == "Bad frames=0"
            assert page.inner_text("#decode-errors") == "Decode errors=1"
            for selector, _, label in CHOSEN.values():
                assert page.inner_text(selector) == label, selector
            assert page.inner_text("#pose") == "Pose=10.00,8.00,4.00"
            assert page.inner_text("#plan") == "Plan=room @ z 4.00 m"
            obs = page.inner_text("#obs")
            assert obs.startswith("Obs=") and obs.endswith(" ms")
            age_ms = float(obs.removeprefix("Obs=").removesuffix(" ms"))
            # the frame's own age (stamped 1.5 s before sending), not the time since it arrived
            assert 1500.0 <= age_ms <= (time.time() - stamped) * 1000.0 + 1.0
            assert not page.is_visible("#waiting")
            # The heat map holds the corridor: straight ahead (centre column) is far/dark, the sides near/bright.
            ahead, side = pixel(page, "heatmap", 64, 24)[0], pixel(page, "heatmap", 1, 24)[0]
            assert ahead < 60 < side
            # The trail canvas (384 px for the 16 m plan: 24 px per meter, y up): the current position is
            # red, the path behind it cyan, the wall ring black, open floor bright.
            assert page.get_attribute("#trail", "data-plan") == "1"
            assert page.get_attribute("#trail", "data-points") == "40"
            r, g, b = pixel(page, "trail", 240, 192)  # (10, 8) m
            assert r > 200 and g < 80 and b < 80, (r, g, b)
            r, g, b = pixel(page, "trail", 144, 192)  # (6, 8) m, on the path
            assert r < 60 and g > 150 and b > 200, (r, g, b)
            assert pixel(page, "trail", 5, 380) == [0, 0, 0]  # (0.2, 0.2) m: the wall
            assert min(pixel(page, "trail", 96, 96)) >= 200  # (4, 12) m: open floor
            page.screenshot(path=str(SCREENSHOTS / "auditor_dashboard_training.png"), full_page=True)

            zenoh_client.put(TELEMETRY.key, telemetry("actor.inference.sps", 50.0, 161))
            page.wait_for_function(
                "document.getElementById('mode').textContent === 'INFERENCE'", timeout=WAIT_MS
            )
            page.wait_for_function("document.getElementById('sps').textContent === 'SPS=50'", timeout=WAIT_MS)
            assert (state.snapshot().bad_frames, state.snapshot().decode_errors) == (0, 1)
            browser.close()
    finally:
        server.stop()


def test_explorer_page_flies_the_drone_with_the_keyboard(tmp_path: Path, make_env: Callable[[], Any]) -> None:
    sync_api = browser_api()
    explorer = Explorer(
        [("room", make_env)], ExplorerConfig(max_steps=10_000, tick_hz=20.0, out_dir=tmp_path)
    )
    hub = explorer_hub()
    app = create_app(DashboardState(), Hub(), background=(lambda: explorer.run(hub),),
                     extra=explorer_routes(explorer, hub))  # fmt: skip
    server = BackgroundServer(app, port=0).start()  # the OS picks the port; url names it
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1000, "height": 420})
            page.goto(server.url + "/explore")
            page.wait_for_selector("#link.up", timeout=WAIT_MS)
            page.wait_for_function(
                "Number(document.getElementById('heatmap').dataset.seq) > 0", timeout=WAIT_MS
            )
            seq = "Number(document.getElementById('heatmap').dataset.seq)"  # the flight's step count
            page.keyboard.down("w")
            page.wait_for_function("document.getElementById('held').textContent === 'w'", timeout=WAIT_MS)
            page.wait_for_function(f"{seq} >= {page.evaluate(seq)} + 12", timeout=WAIT_MS)  # 12 steps with W
            page.keyboard.down("q")
            page.wait_for_function("document.getElementById('held').textContent === 'q w'", timeout=WAIT_MS)
            page.wait_for_function(f"{seq} >= {page.evaluate(seq)} + 8", timeout=WAIT_MS)  # 8 with W and Q
            page.screenshot(path=str(SCREENSHOTS / "auditor_explorer.png"))
            page.keyboard.up("q")
            page.keyboard.up("w")
            page.keyboard.press("Escape")
            page.wait_for_function(
                "document.getElementById('waiting').className === 'overlay'", timeout=WAIT_MS
            )
            browser.close()
    finally:
        server.stop()
    demo = load_demo(explorer.saved[0])
    forward = demo.actions[:, 0] == 1.0  # (T,) steps flown with W held
    assert forward.sum() >= 12 + 8 and np.any(demo.actions[:, 3] == 1.0)
    heading = np.array([np.cos(demo.poses[0, 5]), np.sin(demo.poses[0, 5])])
    assert float((demo.poses[-1, :2] - demo.poses[0, :2]) @ heading) > 1.0  # it flew forward, metres
