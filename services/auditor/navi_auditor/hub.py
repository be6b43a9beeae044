"""WebSocket fan-out: one bounded drop-oldest queue per browser, so a slow browser stalls nobody.

The hub lives on the server's asyncio loop. A broadcaster task renders the dashboard state at a fixed
rate into one JSON text message and offers it to every client queue; each client's sender coroutine
drains its own queue. A full queue drops its oldest message (the page only needs the newest).
"""

from __future__ import annotations

import asyncio
import base64
import json
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

from navi_auditor.state import DashboardState, Snapshot


@dataclass(frozen=True)
class HubConfig:
    """Push rate and queue bounds of the WebSocket hub."""

    rate_hz: float = 8.0
    """Dashboard pushes per second (the heat map refreshes at this rate, 5-10 Hz)."""
    queue_size: int = 4
    """Messages each client may have waiting; older ones are dropped first."""


class ClientQueue:
    """A bounded FIFO of outgoing messages for one client; `put` never waits and drops the oldest."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be at least 1")
        self._items: deque[str] = deque(maxlen=maxsize)
        self._ready = asyncio.Event()
        self.dropped = 0
        self.delivered = 0

    def put(self, message: str) -> None:
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(message)
        self._ready.set()

    async def get(self) -> str:
        while not self._items:
            self._ready.clear()
            await self._ready.wait()
        self.delivered += 1
        return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class Hub:
    """The set of connected clients and the messages they are offered."""

    config: HubConfig = field(default_factory=HubConfig)
    clients: set[ClientQueue] = field(default_factory=set)

    def connect(self) -> ClientQueue:
        queue = ClientQueue(self.config.queue_size)
        self.clients.add(queue)
        return queue

    def disconnect(self, queue: ClientQueue) -> None:
        self.clients.discard(queue)

    def broadcast(self, message: str) -> None:
        for queue in self.clients:
            queue.put(message)


def snapshot_message(snap: Snapshot) -> str:
    """Render a snapshot as the page's JSON message (the frame as base64 uint8, row-major (El, Az/2);
    the floor plan as base64 uint8, row-major (H, W), row 0 at the smallest y)."""
    body: dict[str, Any] = {
        "type": "dashboard",
        "mode": snap.mode.value,
        "obs_age_ms": None if snap.obs_age_ms is None else round(snap.obs_age_ms, 1),
        "sps": snap.sps,
        "actors": snap.actors,
        "run_id": snap.run_id,
        "step": snap.step,
        "frames": snap.frames,
        "bad_frames": snap.bad_frames,
        "decode_errors": snap.decode_errors,
        "charts": snap.charts,
        "corpus": None if snap.corpus is None else asdict(snap.corpus),
        "pose": None
        if snap.pose is None
        else {"x": snap.pose.x, "y": snap.pose.y, "z": snap.pose.z, "yaw": snap.pose.yaw},
        "trail": [[round(x, 3), round(y, 3)] for x, y in snap.trail],
        "plan": None,
        "frame": None,
    }
    if snap.plan is not None:
        plan = snap.plan
        height, width = plan.pixels.shape
        body["plan"] = {
            "seq": plan.seq,
            "scene": plan.scene,
            "origin_x": plan.origin_x,
            "origin_y": plan.origin_y,
            "cell_size": plan.cell_size,
            "z": plan.z,
            "width": width,
            "height": height,
            "data": base64.b64encode(plan.pixels.tobytes()).decode("ascii"),
        }
    if snap.frame is not None:
        height, width = snap.frame.pixels.shape
        body["frame"] = {
            "seq": snap.frame.seq,
            "step_id": snap.frame.step_id,
            "width": width,
            "height": height,
            "data": base64.b64encode(snap.frame.pixels.tobytes()).decode("ascii"),
        }
    return json.dumps(body, allow_nan=False, separators=(",", ":"))


async def broadcast_forever(state: DashboardState, hub: Hub) -> None:
    """Push the dashboard state to every client at `hub.config.rate_hz` until cancelled."""
    period = 1.0 / hub.config.rate_hz
    while True:
        if hub.clients:
            hub.broadcast(snapshot_message(state.snapshot(time.monotonic())))
        await asyncio.sleep(period)
