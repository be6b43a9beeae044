"""The explorer: keys -> actions, flights through real SdfDagEnv scenes, demonstrations on disk."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from navi_auditor.dashboard import create_app
from navi_auditor.demos import DemoFormatError, load_demo, load_demos, save_arrays
from navi_auditor.explorer import (
    Explorer,
    ExplorerConfig,
    ExplorerEnv,
    explorer_hub,
    explorer_routes,
    keys_to_action,
)
from navi_auditor.hub import Hub
from navi_auditor.state import DashboardState


def test_keys_map_to_body_frame_actions() -> None:
    np.testing.assert_array_equal(keys_to_action(frozenset()), [0, 0, 0, 0])
    np.testing.assert_array_equal(keys_to_action(frozenset({"w", "a", " ", "q"})), [1, 1, 1, 1])
    np.testing.assert_array_equal(keys_to_action(frozenset({"s", "d", "shift", "e"})), [-1, -1, -1, -1])
    np.testing.assert_array_equal(
        keys_to_action(frozenset({"w", "s", "q"})), [0, 0, 0, 1]
    )  # opposites cancel


def test_flights_record_valid_demonstrations(tmp_path: Path, make_env: Callable[[], ExplorerEnv]) -> None:
    explorer = Explorer(
        [("room-a", make_env), ("room-b", make_env)], ExplorerConfig(max_steps=6, out_dir=tmp_path / "demos")
    )
    explorer.set_keys(frozenset({"w", "ctrl"}))  # unknown keys are ignored
    for _ in range(6):
        assert explorer.step_once()
    assert len(explorer.saved) == 1  # the step limit closed scene 1
    explorer.set_keys(frozenset({"q"}))
    for _ in range(3):
        assert explorer.step_once()
    explorer.handle(json.dumps({"type": "next"}))  # ESC
    explorer.handle("not json")
    assert explorer.step_once()
    assert not explorer.step_once() and explorer.finished.is_set()

    first, second = (load_demo(p) for p in explorer.saved)
    assert first.steps == 6 and second.steps == 3
    assert first.scene == "room-a" and second.scene == "room-b"
    assert first.obs_shape == (3, 32, 8)
    np.testing.assert_array_equal(first.actions, np.tile([1.0, 0.0, 0.0, 0.0], (6, 1)))
    heading = np.array([math.cos(first.poses[0, 5]), math.sin(first.poses[0, 5])])
    assert np.all(np.diff(first.poses[:, :2] @ heading) > 0)  # W flies forward along the heading
    assert np.all(np.diff(np.unwrap(second.poses[:, 5])) > 0)  # Q turns left (counter-clockwise)
    assert first.dones[-1] and not first.dones[:-1].any()
    assert len(load_demos(tmp_path / "demos")) == 2


def test_demo_validation_rejects_bad_files(tmp_path: Path) -> None:
    t, az, el = 4, 8, 2
    good = {
        "observations": np.full((t, 3, az, el), 0.5, np.float16),
        "actions": np.zeros((t, 4), np.float32),
        "poses": np.zeros((t, 6), np.float32),
        "rewards": np.zeros(t, np.float32),
        "dones": np.array([False, True, False, True]),
        "episode_starts": np.array([True, False, True, False]),
    }
    save_arrays(tmp_path / "ok.npz", "s", good)
    assert load_demo(tmp_path / "ok.npz").steps == t
    bad_cases = {
        "actions": np.full((t, 4), 1.5, np.float32),  # outside [-1, 1]
        "rewards": np.zeros(t + 1, np.float32),  # wrong length
        "poses": np.zeros((t, 6), np.float64),  # wrong dtype
        "episode_starts": np.array([True, True, False, False]),  # disagrees with dones
        "observations": np.full((t, 3, az, el), np.nan, np.float16),
    }
    for name, value in bad_cases.items():
        with pytest.raises(DemoFormatError):
            save_arrays(tmp_path / f"bad_{name}.npz", "s", {**good, name: value})
    np.savez(tmp_path / "legacy.npz", **good)  # no schema_version
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    for path in ("legacy.npz", "junk.npz"):
        with pytest.raises(DemoFormatError):
            load_demo(tmp_path / path)


def test_explorer_page_websocket_flies_the_drone(tmp_path: Path, make_env: Callable[[], ExplorerEnv]) -> None:
    explorer = Explorer([("room", make_env)], ExplorerConfig(max_steps=1000, tick_hz=50.0, out_dir=tmp_path))
    hub = explorer_hub()
    app = create_app(
        DashboardState(), Hub(), background=(lambda: explorer.run(hub),), extra=explorer_routes(explorer, hub)
    )
    with TestClient(app) as client:
        assert "W/S forward/back" in client.get("/explore").text
        with client.websocket_connect("/ws/explore") as ws:
            ws.send_text(json.dumps({"type": "keys", "pressed": ["w", "q"]}))
            seen = []
            for _ in range(200):
                message = ws.receive_json()
                if message.get("keys") == ["q", "w"]:
                    seen.append(message)
                if len(seen) >= 5:
                    break
            assert len(seen) >= 5
            assert seen[-1]["frame"]["width"] == 16 and seen[-1]["frame"]["height"] == 8
            assert seen[-1]["step"] > seen[0]["step"]
            ws.send_text(json.dumps({"type": "next"}))
            for _ in range(200):
                if ws.receive_json()["finished"]:
                    break
    assert explorer.finished.is_set() and len(explorer.saved) == 1
    demo = load_demo(explorer.saved[0])
    assert np.any(np.all(demo.actions == [1.0, 0.0, 0.0, 1.0], axis=1))
