"""The auditor's web app: the dashboard page, its WebSocket, and (when given) the explorer page.

`create_app` takes an in-process `DashboardState` and `Hub`; whatever feeds the state (the Zenoh feed
in `feed.py`, a replay, a test) is outside. The app only reads: it never publishes to env or learner.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Coroutine
from dataclasses import asdict
from importlib import resources
from pathlib import Path
from typing import Any

from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from navi_auditor.hub import ClientQueue, Hub, broadcast_forever, snapshot_message
from navi_auditor.state import DashboardState

STATIC_DIR = Path(str(resources.files("navi_auditor") / "static"))

Background = Callable[[], Coroutine[Any, Any, None]]


async def pump(
    websocket: WebSocket, queue: ClientQueue, on_text: Callable[[str], None] | None = None
) -> None:
    """Send queued messages until the client goes away; incoming text goes to `on_text` (else ignored)."""

    async def send_all() -> None:
        while True:
            await websocket.send_text(await queue.get())

    async def until_closed() -> None:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            if on_text is not None and message.get("text"):
                on_text(message["text"])

    tasks = [asyncio.create_task(send_all()), asyncio.create_task(until_closed())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, OSError, RuntimeError):
                await task


def create_app(
    state: DashboardState,
    hub: Hub,
    background: tuple[Background, ...] = (),
    extra: Callable[[FastAPI], None] | None = None,
) -> FastAPI:
    """The FastAPI app. `background` coroutines run for the app's lifetime; `extra` adds routes."""

    @contextlib.asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        tasks = [asyncio.create_task(broadcast_forever(state, hub))]
        tasks += [asyncio.create_task(job()) for job in background]
        try:
            yield
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    app = FastAPI(title="Navi auditor", lifespan=lifespan)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/healthz")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/api/state")
    async def api_state() -> JSONResponse:
        snap = state.snapshot(time.monotonic())
        body: dict[str, Any] = {
            "mode": snap.mode.value,
            "obs_age_ms": snap.obs_age_ms,
            "sps": snap.sps,
            "actors": snap.actors,
            "run_id": snap.run_id,
            "step": snap.step,
            "frames": snap.frames,
            "bad_frames": snap.bad_frames,
            "decode_errors": snap.decode_errors,
            "corpus": None if snap.corpus is None else asdict(snap.corpus),
            "pose": None if snap.pose is None else {"x": snap.pose.x, "y": snap.pose.y, "z": snap.pose.z},
            "trail_points": len(snap.trail),
            "plan_scene": None if snap.plan is None else snap.plan.scene,
            "latest": {
                chart: {key: points[-1][1] for key, points in series.items() if points}
                for chart, series in snap.charts.items()
            },
            "clients": len(hub.clients),
        }
        return JSONResponse(body)

    @app.websocket("/ws")
    async def dashboard_socket(websocket: WebSocket) -> None:
        await websocket.accept()
        queue = hub.connect()
        queue.put(snapshot_message(state.snapshot(time.monotonic())))
        try:
            await pump(websocket, queue)
        finally:
            hub.disconnect(queue)

    if extra is not None:
        extra(app)
    return app
