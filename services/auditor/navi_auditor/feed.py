"""The thin Zenoh part of the dashboard: subscribe to telemetry and observations, feed the state.

Built on navi_mesh: the session comes from NaviSettings (client mode, scouting off, reconnecting after
a router restart), decoding goes through `navi_mesh.pubsub.subscribe`, which drops and counts
undecodable payloads (navi_decode_errors_total). The feed declares its subscribers and the service's
liveliness token, and nothing else: no publisher, querier or queryable, so the auditor cannot steer.
It also subscribes to actor 0's pose and its scene's floor plan (the top-down trail).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any

from navi_auditor.state import DashboardState
from navi_contracts.models import DistanceMatrix, FloorPlan, RobotPose, TelemetryEvent
from navi_contracts.settings import NaviSettings
from navi_contracts.topics import FLOOR_PLAN, OBSERVATIONS, POSES, TELEMETRY

TOPICS = (TELEMETRY, OBSERVATIONS, POSES, FLOOR_PLAN)
"""Everything the dashboard subscribes to."""

log = logging.getLogger("navi.auditor.feed")

SERVICE = "auditor"
"""Liveliness name: the dashboard holds navi/alive/auditor/<instance> while connected."""


def try_open(settings: NaviSettings, timeout_s: float) -> Any | None:
    """A new client session, or None when no router answered within `timeout_s`."""
    from navi_mesh.session import MeshError, config_from_settings, open_new_session

    try:
        return open_new_session(config_from_settings(settings, connect_timeout_s=timeout_s))
    except MeshError as exc:
        log.info("no Zenoh router yet: %s", exc)
        return None


def open_until(settings: NaviSettings, stop: threading.Event, retry_s: float = 1.0) -> Any | None:
    """Keep trying to open a session until one opens (returned) or `stop` is set (None)."""
    while not stop.is_set():
        session = try_open(settings, retry_s)
        if session is not None:
            return session
    return None


def decode_errors() -> int:
    """Undecodable payloads dropped so far on the dashboard's topics (this process)."""
    from navi_mesh.pubsub import decode_error

    return sum(decode_error.counts[topic.key] for topic in TOPICS)


class ZenohFeed:
    """Feeds a `DashboardState` from Zenoh for as long as `run()` is awaited."""

    def __init__(self, state: DashboardState, settings: NaviSettings, retry_s: float = 1.0) -> None:
        self.state = state
        self.settings = settings
        self.retry_s = retry_s

    async def connect(self) -> Any:
        """Open the session, retrying every `retry_s` until a router answers (the page shows WAITING)."""
        while True:
            session = await asyncio.to_thread(try_open, self.settings, self.retry_s)
            if session is not None:
                return session

    async def run(self) -> None:
        """Connect, subscribe, and keep feeding until cancelled."""
        from navi_mesh.liveliness import declare_alive
        from navi_mesh.pubsub import subscribe

        session = await self.connect()
        baseline = decode_errors()  # the counter is per process; the page counts from this dashboard's start
        telemetry: Any = subscribe(session, TELEMETRY, self._on_telemetry)
        observations: Any = subscribe(session, OBSERVATIONS, self._on_observation)
        poses: Any = subscribe(session, POSES, self._on_pose)
        plans: Any = subscribe(session, FLOOR_PLAN, self._on_floor_plan)
        token = declare_alive(session, SERVICE)
        log.info("auditor feed subscribed to %s", ", ".join(t.key for t in TOPICS))
        try:
            while True:
                self.state.set_decode_errors(decode_errors() - baseline)
                await asyncio.sleep(0.5)
        finally:
            token.undeclare()
            for sub in (telemetry, observations, poses, plans):
                sub.undeclare()
            session.close()

    def _on_telemetry(self, event: TelemetryEvent) -> None:
        self.state.on_telemetry(event)

    def _on_observation(self, matrix: DistanceMatrix) -> None:
        self.state.on_observation(matrix)

    def _on_pose(self, pose: RobotPose) -> None:
        self.state.on_pose(pose)

    def _on_floor_plan(self, plan: FloorPlan) -> None:
        self.state.on_floor_plan(plan)
