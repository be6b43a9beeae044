"""Navi wire contracts: message models, the msgpack codec, Zenoh key expressions and settings.

Imported by services only (never by the training hot path).
"""

from navi_contracts.codec import ContractError, decode, decode_any, encode
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
from navi_contracts.settings import NaviSettings

__all__ = [
    "Action",
    "CompileJob",
    "CompileResult",
    "ContractError",
    "DistanceMatrix",
    "FloorPlan",
    "Message",
    "ModelPromoted",
    "NaviSettings",
    "RobotPose",
    "StepRequest",
    "StepResult",
    "TelemetryEvent",
    "decode",
    "decode_any",
    "encode",
]
