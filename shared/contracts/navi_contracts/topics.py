"""Zenoh key expressions: one constant per topic, with its direction, payload and QoS.

Reliability: `reliable` retransmits; `best_effort` may lose samples. Congestion: `drop` lets a
publisher discard samples rather than wait (latest-value streams); `block` makes it wait (data that
must not be lost). Liveliness tokens live under `ALIVE`: `navi/alive/<service>/<instance id>`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from navi_contracts.models import (
    Action,
    CompileJob,
    CompileResult,
    DistanceMatrix,
    FloorPlan,
    Message,
    ModelPromoted,
    RobotPose,
    StepRequest,
    StepResult,
    TelemetryEvent,
)


@dataclass(frozen=True)
class Topic:
    key: str
    direction: str
    payload: type[Message]
    reliability: Literal["reliable", "best_effort"]
    congestion: Literal["drop", "block"]
    reply: type[Message] | None = None  # queryables: the model of the reply


OBSERVATIONS = Topic(
    "navi/env/observations",
    "env or learner -> auditor, external brains (actor 0 at 5-10 Hz from the learner)",
    DistanceMatrix,
    "best_effort",
    "drop",
)
ACTIONS = Topic("navi/actor/actions", "learner or brain -> env, auditor", Action, "best_effort", "drop")
STEP = Topic(
    "navi/env/step",
    "brain -> env (queryable; the env replies)",
    StepRequest,
    "reliable",
    "block",
    reply=StepResult,
)
TELEMETRY = Topic(
    "navi/telemetry",
    "every service -> auditor, recorder (drop-oldest queue at the publisher)",
    TelemetryEvent,
    "best_effort",
    "drop",
)
COMPILE_JOBS = Topic(
    "navi/compiler/jobs",
    "client -> compiler workers (queryable; one worker replies)",
    CompileJob,
    "reliable",
    "block",
    reply=CompileResult,
)
MODEL_PROMOTED = Topic(
    "navi/models/promoted", "control plane -> inference services, auditor", ModelPromoted, "reliable", "block"
)
POSES = Topic(
    "navi/actor/pose",
    "learner -> auditor (actor 0's pose, at the observation rate)",
    RobotPose,
    "best_effort",
    "drop",
)
FLOOR_PLAN = Topic(
    "navi/env/floor_plan",
    "learner -> auditor (the floor plan of actor 0's scene, when it changes and every 5 s)",
    FloorPlan,
    "best_effort",
    "drop",
)
ALIVE = "navi/alive"

ALL_TOPICS: tuple[Topic, ...] = (
    OBSERVATIONS,
    ACTIONS,
    STEP,
    TELEMETRY,
    COMPILE_JOBS,
    MODEL_PROMOTED,
    POSES,
    FLOOR_PLAN,
)


def alive_key(service: str, instance_id: str) -> str:
    """The liveliness token key of one service instance."""
    for part in (service, instance_id):
        if not part or any(c in part for c in "/*$?#"):
            raise ValueError(f"invalid liveliness key part {part!r}")
    return f"{ALIVE}/{service}/{instance_id}"
