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


def test_explorer_shows_moving_obstacles(tmp_path: Path) -> None:
    """With obstacles the message reports them and masks exactly the pixels that see one: a still ball
    of 1.5 m put 3 m straight ahead (+-30 degrees) fills the middle of the forward view."""
    import base64

    import torch

    from navi_env.config import EnvConfig, ObstacleConfig
    from navi_env.sim.env import SdfDagEnv
    from navi_env.tracer import primitives as ob

    from .conftest import room_corpus

    config = EnvConfig(
        azimuth_bins=32, elevation_bins=8, obstacles=ObstacleConfig(count=1, shapes=("sphere",))
    )
    spawns = [torch.tensor([[8.0, 8.0, 4.0], [4.0, 4.0, 4.0], [12.0, 12.0, 4.0]])]
    envs: list[SdfDagEnv] = []

    def make() -> SdfDagEnv:
        envs.append(SdfDagEnv(room_corpus(), 1, "cpu", config, spawns=spawns))
        return envs[-1]

    explorer = Explorer([("room", make)], ExplorerConfig(max_steps=50, out_dir=tmp_path))
    explorer.step_once()
    env = envs[0]
    assert env.obstacles is not None
    yaw = float(env.yaw[0])
    ahead = env.position[0] + 3.0 * torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
    env.obstacles.prims[0, 0] = ob.record(ob.SPHERE, ahead.tolist(), radius=1.5)
    env.obstacles.anchor[0, 0] = ahead  # a linear script with speed 0: it stays there
    env.obstacles.phase.zero_()
    env.obstacles.speed.zero_()
    env.obstacles.bound.fill_(1.5)
    explorer.step_once()
    message = json.loads(explorer.view_message())
    seen = message["obstacles"]
    assert seen["active"] == 1 and seen["collisions"] == 0
    assert seen["nearest"] == pytest.approx(1.5, abs=0.01)
    mask = np.frombuffer(base64.b64decode(seen["mask"]), dtype=np.uint8).reshape(8, 16)  # (El, Az/2)
    assert mask[3:5, 7:9].all()  # straight ahead, at the horizon
    assert not mask[:, :3].any() and not mask[:, -3:].any()  # nothing to the sides
    assert mask.sum() < mask.size // 4
