"""The live dashboard in a real headless Chromium, fed over a real Zenoh router on loopback.

The page must show WAITING first, then frames and the right mode (TRAINING, then INFERENCE) once a
publisher starts sending encoded TelemetryEvents and DistanceMatrix messages.
"""

from __future__ import annotations

import socket
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
from navi_contracts.models import DistanceMatrix, TelemetryEvent
from navi_contracts.settings import NaviSettings
from navi_contracts.topics import OBSERVATIONS, TELEMETRY

CHROMIUM = Path("/usr/bin/chromium")
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

pytestmark = pytest.mark.integration


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def corridor(az: int, el: int, step: int) -> DistanceMatrix:
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
        timestamp=time.time(),
        run_id="browser-test",
    )


def telemetry(key: str, value: float, step: int) -> bytes:
    return encode(
        TelemetryEvent(key=key, value=value, step=step, run_id="browser-test", timestamp=time.time())
    )


def browser_api() -> Any:
    """Playwright's sync API, or a skip naming what is missing (never downloads a browser)."""
    if not CHROMIUM.exists():
        pytest.skip("Debian's chromium is not installed at /usr/bin/chromium (apt-get install -y chromium)")
    return pytest.importorskip("playwright.sync_api", reason="the playwright Python package is not installed")


def test_browser_shows_waiting_then_frames_and_mode(zenoh_router: NaviSettings, zenoh_client: Any) -> None:
    sync_api = browser_api()
    app, state = build_live_app(zenoh_router, AuditorConfig())
    server = BackgroundServer(app, port=free_port()).start()
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1400, "height": 560})
            page.goto(server.url)
            page.wait_for_selector("#link.up", timeout=10_000)
            assert page.inner_text("#mode") == "WAITING"
            assert page.get_attribute("#heatmap", "data-seq") == "0"
            assert page.is_visible("#waiting")
            SCREENSHOTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SCREENSHOTS / "auditor_dashboard_waiting.png"))

            for step in range(40):
                zenoh_client.put(TELEMETRY.key, telemetry("actor.training.sps", 900.0 + step, step))
                zenoh_client.put(
                    TELEMETRY.key, telemetry("actor.training.reward_ema", -1.0 + 0.05 * step, step)
                )
                zenoh_client.put(TELEMETRY.key, telemetry("actor.training.actors", 4.0, step))
                zenoh_client.put(OBSERVATIONS.key, encode(corridor(256, 48, step)))
                time.sleep(0.05)
            page.wait_for_function(
                "document.getElementById('mode').textContent === 'TRAINING'", timeout=10_000
            )
            page.wait_for_function(
                "Number(document.getElementById('heatmap').dataset.seq) >= 20", timeout=10_000
            )
            page.wait_for_function("document.getElementById('sps').textContent === 'SPS=939'", timeout=10_000)
            assert page.inner_text("#actors") == "Actors=4"
            assert page.inner_text("#obs").startswith("Obs=") and page.inner_text("#obs").endswith(" ms")
            assert not page.is_visible("#waiting")
            # The heat map holds the corridor: straight ahead (centre column) is far/dark, the sides near/bright.
            ahead, side = page.evaluate(
                "(() => { const c = document.getElementById('heatmap').getContext('2d');"
                " return [c.getImageData(64, 24, 1, 1).data[0], c.getImageData(1, 24, 1, 1).data[0]]; })()"
            )
            assert ahead < 60 < side
            page.screenshot(path=str(SCREENSHOTS / "auditor_dashboard_training.png"))

            zenoh_client.put(TELEMETRY.key, telemetry("actor.inference.sps", 50.0, 41))
            page.wait_for_function(
                "document.getElementById('mode').textContent === 'INFERENCE'", timeout=10_000
            )
            assert state.snapshot().rejected == 0
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
    server = BackgroundServer(app, port=free_port()).start()
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1000, "height": 420})
            page.goto(server.url + "/explore")
            page.wait_for_selector("#link.up", timeout=10_000)
            page.wait_for_function(
                "Number(document.getElementById('heatmap').dataset.seq) > 0", timeout=10_000
            )
            page.keyboard.down("w")
            page.wait_for_function("document.getElementById('held').textContent === 'w'", timeout=10_000)
            page.wait_for_timeout(600)
            page.keyboard.down("q")
            page.wait_for_timeout(400)
            page.screenshot(path=str(SCREENSHOTS / "auditor_explorer.png"))
            page.keyboard.up("q")
            page.keyboard.up("w")
            page.keyboard.press("Escape")
            page.wait_for_function(
                "document.getElementById('waiting').className === 'overlay'", timeout=10_000
            )
            browser.close()
    finally:
        server.stop()
    demo = load_demo(explorer.saved[0])
    forward = demo.actions[:, 0] == 1.0  # (T,) steps flown with W held
    assert forward.sum() >= 5 and np.any(demo.actions[:, 3] == 1.0)
    heading = np.array([np.cos(demo.poses[0, 5]), np.sin(demo.poses[0, 5])])
    assert float((demo.poses[-1, :2] - demo.poses[0, :2]) @ heading) > 1.0  # it flew forward, metres
