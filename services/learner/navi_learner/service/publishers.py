"""The learner service's publishers on the mesh (drop-oldest queues drained by their own threads, so
the loop never waits on Zenoh) and the telemetry events of a log row."""

from __future__ import annotations

import numpy as np
import zenoh

from navi_contracts.models import (
    Action,
    DistanceMatrix,
    FloorPlan,
    ModelPromoted,
    RobotPose,
    TelemetryEvent,
)
from navi_contracts.topics import ACTIONS, FLOOR_PLAN, MODEL_PROMOTED, OBSERVATIONS, POSES, TELEMETRY
from navi_mesh.messages import telemetry
from navi_mesh.pubsub import Publisher, QueuedPublisher


class MeshPublishers:
    """The learner's publishers over one session."""

    def __init__(self, sess: zenoh.Session, telemetry_capacity: int) -> None:
        self.telemetry: QueuedPublisher[TelemetryEvent] = QueuedPublisher(sess, TELEMETRY, telemetry_capacity)
        self.observations: QueuedPublisher[DistanceMatrix] = QueuedPublisher(sess, OBSERVATIONS, capacity=2)
        self.actions: QueuedPublisher[Action] = QueuedPublisher(sess, ACTIONS, capacity=2)
        self.poses: QueuedPublisher[RobotPose] = QueuedPublisher(sess, POSES, capacity=2)
        self.floor_plans: QueuedPublisher[FloorPlan] = QueuedPublisher(sess, FLOOR_PLAN, capacity=1)
        self.promotions: Publisher[ModelPromoted] = Publisher(sess, MODEL_PROMOTED)

    def close(self) -> None:
        for pub in (self.telemetry, self.observations, self.actions, self.poses, self.floor_plans):
            pub.close()
        self.promotions.close()


def telemetry_rows(prefix: str, row: dict[str, float], run_id: str) -> list[TelemetryEvent]:
    """A log row -> one TelemetryEvent per finite value, keyed `<prefix>.<name>`."""
    step = int(row.get("step", 0))
    return [
        telemetry(f"{prefix}.{name}", value, step, run_id)
        for name, value in row.items()
        if name != "step" and np.isfinite(value)
    ]
