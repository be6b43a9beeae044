"""`navi explore`: fly one drone by keyboard through scenes in the browser, recording demonstrations.

The server owns a one-actor SdfDagEnv per scene. The page (/explore) sends the set of held keys over
its WebSocket; the server steps the env at `tick_hz` with the action those keys mean, pushes the view
back, and appends every step to a demonstration buffer. After `max_steps` steps (or ESC) the flight is
written to `<out_dir>/<time>_<scene>.npz` (layout in demos.py) and the next scene opens.

Keys: W/S forward/back, A/D left/right, Space/Shift up/down, Q/E yaw left/right, ESC next scene.

With moving obstacles (`navi explore --obstacles K`) every message also carries `obstacles`: how many
are active, the distance to the nearest, the collisions with them so far, and a mask of the view's
pixels that see one (the page tints them).
"""

from __future__ import annotations

import asyncio
import base64
import json
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from fastapi import FastAPI, WebSocket

from navi_auditor.dashboard import STATIC_DIR, pump
from navi_auditor.demos import DemoBuffer
from navi_auditor.hub import Hub, HubConfig
from navi_auditor.state import forward_hemisphere, quantise

KEY_AXES: tuple[tuple[str, int, float], ...] = (
    ("w", 0, 1.0),
    ("s", 0, -1.0),
    (" ", 1, 1.0),
    ("shift", 1, -1.0),
    ("a", 2, 1.0),
    ("d", 2, -1.0),
    ("q", 3, 1.0),
    ("e", 3, -1.0),
)
"""(key, action index, sign): action = [forward, vertical, lateral (+ left), yaw (+ left/CCW)]."""
KNOWN_KEYS = frozenset(k for k, _, _ in KEY_AXES)


def keys_to_action(pressed: frozenset[str]) -> np.ndarray:
    """Held keys -> action (4,) float32 in [-1, 1]; opposite keys cancel."""
    action = np.zeros(4, dtype=np.float32)  # (4,)
    for key, axis, sign in KEY_AXES:
        if key in pressed:
            action[axis] += sign
    return np.clip(action, -1.0, 1.0)


class ExplorerEnv(Protocol):
    """What the explorer needs of navi_env.sim.env.SdfDagEnv with one actor."""

    position: torch.Tensor  # (1, 3)
    yaw: torch.Tensor  # (1,)

    def reset(self, seed: int | None = None) -> torch.Tensor: ...

    def step(self, actions: torch.Tensor) -> Any: ...


@dataclass(frozen=True)
class ExplorerConfig:
    """An exploration session."""

    max_steps: int = 600
    """Steps per scene; then the flight is saved and the next scene opens."""
    tick_hz: float = 10.0
    """Env steps per second while flying (the env's dt is the simulated time per step)."""
    out_dir: Path = Path("artifacts/demonstrations")
    """Where demonstrations are written."""
    seed: int = 0
    """Env seed of the first scene (scene i uses seed + i)."""


@dataclass
class Flight:
    """The scene being flown."""

    index: int
    name: str
    env: ExplorerEnv
    obs: np.ndarray  # (3, Az, El) float32, the current view
    buffer: DemoBuffer
    steps: int = 0
    episode_return: float = 0.0
    last_reward: float = 0.0
    obstacle_collisions: int = 0


@dataclass
class Explorer:
    """Scenes, the current flight, the held keys; `step_once` is the whole per-tick logic."""

    scenes: Sequence[tuple[str, Callable[[], ExplorerEnv]]]
    config: ExplorerConfig = field(default_factory=ExplorerConfig)
    saved: list[Path] = field(default_factory=list)
    finished: threading.Event = field(default_factory=threading.Event)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _pressed: frozenset[str] = frozenset()
    _skip: bool = False
    _flight: Flight | None = None
    _next_index: int = 0

    def set_keys(self, pressed: frozenset[str]) -> None:
        with self._lock:
            self._pressed = pressed & KNOWN_KEYS

    def request_next_scene(self) -> None:
        with self._lock:
            self._skip = True

    def _open_next(self) -> Flight | None:
        if self._next_index >= len(self.scenes):
            self.finished.set()
            return None
        name, make_env = self.scenes[self._next_index]
        env = make_env()
        obs = (
            env.reset(seed=self.config.seed + self._next_index)[0].detach().cpu().numpy().copy()
        )  # (3, Az, El)
        flight = Flight(self._next_index, name, env, obs, DemoBuffer(scene=name))
        self._next_index += 1
        return flight

    def _close(self, flight: Flight) -> None:
        if len(flight.buffer):
            flight.buffer.end_episode()
            stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
            safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in Path(flight.name).stem)
            path = self.config.out_dir / f"{stamp}_{flight.index:03d}_{safe}.npz"
            self.saved.append(flight.buffer.save(path))

    def step_once(self) -> bool:
        """Advance the current flight by one step (opening/closing scenes); False once all are flown."""
        with self._lock:
            pressed, skip, self._skip = self._pressed, self._skip, False
        if self._flight is None:
            self._flight = self._open_next()
            if self._flight is None:
                return False
        flight = self._flight
        if skip:
            self._close(flight)
            self._flight = None
            return True
        action = keys_to_action(pressed)  # (4,)
        position = flight.env.position[0].detach().cpu().numpy()  # (3,)
        yaw = float(flight.env.yaw[0])
        pose = np.array([*position, 0.0, 0.0, yaw], dtype=np.float32)  # (6,) x, y, z, roll, pitch, yaw
        out = flight.env.step(torch.from_numpy(action)[None])
        reward, done = float(out.reward[0]), bool(out.done[0]) or bool(out.truncated[0])
        flight.buffer.add(flight.obs, action, pose, reward, done)
        flight.obs = out.obs[0].detach().cpu().numpy().copy()  # (3, Az, El)
        flight.steps += 1
        flight.last_reward = reward
        if "obstacle_collision" in out.info:
            flight.obstacle_collisions += int(out.info["obstacle_collision"][0])
        flight.episode_return = 0.0 if done else flight.episode_return + reward
        if flight.steps >= self.config.max_steps:
            self._close(flight)
            self._flight = None
        return True

    def view_message(self) -> str:
        """The explorer page's JSON message: the forward view and the flight's status."""
        flight = self._flight
        with self._lock:
            pressed = sorted(self._pressed)
        body: dict[str, Any] = {
            "type": "explorer",
            "finished": self.finished.is_set(),
            "scenes": len(self.scenes),
            "saved": [p.name for p in self.saved],
            "keys": pressed,
        }
        if flight is not None:
            pixels = quantise(forward_hemisphere(flight.obs[0]))  # (El, Az/2) uint8
            position = flight.env.position[0].detach().cpu().numpy()  # (3,)
            body.update(
                {
                    "scene": flight.name,
                    "scene_index": flight.index,
                    "step": flight.steps,
                    "max_steps": self.config.max_steps,
                    "reward": flight.last_reward,
                    "episode_return": flight.episode_return,
                    "position": [round(float(v), 2) for v in position],
                    "yaw": round(float(flight.env.yaw[0]), 3),
                    "frame": {
                        "seq": flight.steps,
                        "width": pixels.shape[1],
                        "height": pixels.shape[0],
                        "data": base64.b64encode(pixels.tobytes()).decode("ascii"),
                    },
                }
            )
            seen = obstacle_view(flight)
            if seen is not None:
                body["obstacles"] = seen
        return json.dumps(body, allow_nan=False, separators=(",", ":"))

    def handle(self, text: str) -> None:
        """Apply one page message: {"type": "keys", "pressed": [...]} or {"type": "next"}; ignore others."""
        try:
            message = json.loads(text)
        except json.JSONDecodeError:
            return
        if not isinstance(message, dict):
            return
        if message.get("type") == "keys" and isinstance(message.get("pressed"), list):
            self.set_keys(frozenset(str(k).lower() for k in message["pressed"] if isinstance(k, str)))
        elif message.get("type") == "next":
            self.request_next_scene()

    async def run(self, hub: Hub) -> None:
        """Step at tick_hz (env work on a worker thread) and push the view, until all scenes are flown."""
        period = 1.0 / self.config.tick_hz
        while True:
            started = time.monotonic()
            more = await asyncio.to_thread(self.step_once)
            hub.broadcast(await asyncio.to_thread(self.view_message))
            if not more:
                self.finished.set()
                return
            await asyncio.sleep(max(0.0, period - (time.monotonic() - started)))


def explorer_routes(explorer: Explorer, hub: Hub) -> Callable[[FastAPI], None]:
    """Routes of the explorer page: GET /explore and the WebSocket /ws/explore."""

    def add(app: FastAPI) -> None:
        from fastapi.responses import FileResponse

        @app.get("/explore", include_in_schema=False)
        async def explore_page() -> FileResponse:
            return FileResponse(STATIC_DIR / "explore.html")

        @app.websocket("/ws/explore")
        async def explore_socket(websocket: WebSocket) -> None:
            await websocket.accept()
            queue = hub.connect()
            try:
                await pump(websocket, queue, explorer.handle)
            finally:
                hub.disconnect(queue)
                explorer.set_keys(frozenset())

    return add


def explorer_hub() -> Hub:
    """The explorer's own hub: one pushed view per tick, at most two waiting per page."""
    return Hub(HubConfig(queue_size=2))


def obstacle_view(flight: Flight) -> dict[str, Any] | None:
    """The flight's moving obstacles for the page (None without any): active count, nearest distance
    (m), collisions so far, and a base64 (El, Az/2) uint8 mask (1 = this pixel sees an obstacle)."""
    env: Any = flight.env
    state = getattr(env, "obstacles", None)
    if state is None:
        return None
    from navi_env.sim.obstacles import obstacle_distance
    from navi_env.tracer import primitives as ob

    code = env.config.obstacles.semantic_class + 1
    az, el = flight.obs.shape[1], flight.obs.shape[2]
    seen = (env.semantic[0] == code).view(az, el).cpu().numpy().astype(np.uint8)  # (Az, El) in obs order
    mask = forward_hemisphere(seen)  # (El, Az/2)
    nearest = float(obstacle_distance(state, env.position)[0])
    return {
        "active": int((state.prims[0, :, ob.KIND] != ob.NONE).sum()),
        "nearest": round(nearest, 2) if nearest != float("inf") else None,
        "collisions": flight.obstacle_collisions,
        "mask": base64.b64encode(mask.tobytes()).decode("ascii"),
    }


def scene_env(path: Path, device: str, obstacles: int = 0) -> Callable[[], ExplorerEnv]:
    """A factory of a one-actor SdfDagEnv over one .gmdag (spawns from the env's qualification), with
    `obstacles` scripted moving obstacles."""

    def make() -> ExplorerEnv:
        from navi_env.config import EnvConfig, ObstacleConfig
        from navi_env.sim.env import SdfDagEnv
        from navi_env.tracer.scene import load_scene

        config = EnvConfig(obstacles=ObstacleConfig(count=obstacles))
        return SdfDagEnv(load_scene(path, device), 1, device, config)

    return make


def run_explorer(
    paths: Sequence[Path],
    max_steps: int,
    out_dir: Path,
    host: str,
    port: int,
    device: str,
    obstacles: int = 0,
) -> list[Path]:
    """Serve the explorer page until every scene is flown (or Ctrl+C); returns the saved demonstrations."""
    from navi_auditor.dashboard import create_app
    from navi_auditor.server import BackgroundServer
    from navi_auditor.state import DashboardState

    explorer = Explorer(
        [(str(p), scene_env(p, device, obstacles)) for p in paths],
        ExplorerConfig(max_steps=max_steps, out_dir=out_dir),
    )
    hub = explorer_hub()
    app = create_app(
        DashboardState(), Hub(), background=(lambda: explorer.run(hub),), extra=explorer_routes(explorer, hub)
    )
    server = BackgroundServer(app, host, port).start()
    print(
        f"explorer: open {server.url}/explore ({len(paths)} scene(s), {max_steps} steps each)",
        file=sys.stderr,
    )
    try:
        while not explorer.finished.wait(0.5):
            pass
    except KeyboardInterrupt:
        print("explorer: interrupted", file=sys.stderr)
    finally:
        server.stop()
    return list(explorer.saved)
