"""`navi serve auditor`: the dashboard web server fed by the Zenoh feed (passive: subscribe only).

`serve(host, port, settings)` is the service entry point. `BackgroundServer` runs any auditor app on a
thread (tests and the explorer use it). Both bind their socket before serving: port 0 takes one the OS
picks, and the bound address is logged (`serve`) or in `url` (`BackgroundServer`).
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass, field

import uvicorn
from fastapi import FastAPI

from navi_auditor.dashboard import create_app
from navi_auditor.feed import ZenohFeed
from navi_auditor.hub import Hub, HubConfig
from navi_auditor.state import DashboardConfig, DashboardState
from navi_contracts.settings import NaviSettings


@dataclass(frozen=True)
class AuditorConfig:
    """The live dashboard service."""

    dashboard: DashboardConfig = field(default_factory=DashboardConfig)
    """What the state machine reads from telemetry and how long streams stay fresh."""
    hub: HubConfig = field(default_factory=HubConfig)
    """WebSocket push rate and per-client queue bound."""


def add_metrics_route(app: FastAPI) -> None:
    """GET /metrics: the auditor's Prometheus metrics (the mesh families: received messages, decode errors, ...)."""
    from fastapi.responses import Response

    from navi_mesh.metrics import exposition

    @app.get("/metrics", include_in_schema=False)
    async def metrics() -> Response:
        body, content_type = exposition("auditor")
        return Response(content=body, media_type=content_type)


def build_live_app(settings: NaviSettings, config: AuditorConfig) -> tuple[FastAPI, DashboardState]:
    """The dashboard app with a Zenoh feed that starts and stops with it, plus /metrics."""
    state = DashboardState(config.dashboard)
    feed = ZenohFeed(state, settings)
    app = create_app(state, Hub(config.hub), background=(feed.run,), extra=add_metrics_route)
    return app, state


log = logging.getLogger("navi_auditor.server")


def serve(host: str, port: int, settings: NaviSettings, config: AuditorConfig | None = None) -> None:
    """Run the live dashboard until interrupted (blocks); port 0 takes one the OS picks."""
    app, _ = build_live_app(settings, config or AuditorConfig())
    server_config = uvicorn.Config(app, host=host, port=port, log_level="warning")
    sock = server_config.bind_socket()  # exits 1 with uvicorn's error line when the port is taken
    log.info("auditor dashboard listening on http://%s:%d", host, sock.getsockname()[1])
    server = uvicorn.Server(server_config)
    server.run(sockets=[sock])
    if not server.started:
        raise SystemExit(3)  # uvicorn's startup failure code


class BackgroundServer:
    """An auditor app served by uvicorn on a daemon thread; `stop()` shuts it down. The socket is bound
    here (port 0: one the OS picks); `url` and `port` name the bound address."""

    def __init__(self, app: FastAPI, host: str = "127.0.0.1", port: int = 8080) -> None:
        self._socket = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._socket.bind((host, port))
        except OSError as err:
            self._socket.close()
            raise RuntimeError(f"the auditor server cannot listen on {host}:{port}: {err}") from err
        self.port = int(self._socket.getsockname()[1])
        self.url = f"http://{host}:{self.port}"
        self._server = uvicorn.Server(uvicorn.Config(app, host=host, port=self.port, log_level="warning"))
        self._thread = threading.Thread(
            target=self._server.run, kwargs={"sockets": [self._socket]}, name="navi-auditor-http", daemon=True
        )

    def start(self, timeout_s: float = 10.0) -> BackgroundServer:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise RuntimeError(f"the auditor server did not start on {self.url}")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=10.0)
        self._socket.close()
