"""Wire messages: one pydantic v2 model per message, each carrying its `schema_version`.

Arrays are numpy arrays with a fixed dtype and a shape checked against the model's own sizes.
Shapes: N environments (actors), Az azimuth bins, El elevation bins.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    model_validator,
)


def _checked(dtype: str, ndim: int) -> Callable[[Any], np.ndarray]:
    """A validator accepting only numpy arrays of exactly this dtype and rank (never copies)."""
    want = np.dtype(dtype)

    def check(value: Any) -> np.ndarray:
        if not isinstance(value, np.ndarray):
            raise ValueError(f"expected a numpy array of {want}, got {type(value).__name__}")
        if value.dtype != want:
            raise ValueError(f"expected dtype {want}, got {value.dtype}")
        if value.ndim != ndim:
            raise ValueError(f"expected a {ndim}-d array, got shape {value.shape}")
        return value

    return check


_as_is = PlainSerializer(lambda a: a, return_type=Any)  # arrays stay arrays for the codec
F32_1D = Annotated[np.ndarray, PlainValidator(_checked("float32", 1)), _as_is]
F32_2D = Annotated[np.ndarray, PlainValidator(_checked("float32", 2)), _as_is]
F32_3D = Annotated[np.ndarray, PlainValidator(_checked("float32", 3)), _as_is]
I32_1D = Annotated[np.ndarray, PlainValidator(_checked("int32", 1)), _as_is]
BOOL_1D = Annotated[np.ndarray, PlainValidator(_checked("bool", 1)), _as_is]


class Message(BaseModel):
    """Base of every wire model: frozen, strict about unknown fields, numpy-friendly."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    @classmethod
    def schema_version_of(cls) -> int:
        """The one schema version this model reads and writes."""
        default = cls.model_fields["schema_version"].default
        assert isinstance(default, int)
        return default


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError("must be finite")
    return value


Finite = Annotated[float, AfterValidator(_finite)]


class DistanceMatrix(Message):
    """Spherical distance observation of N environments: (N, Az, El) per channel.

    `depth` is distance / horizon in [0, 1]; `semantic` is 0 for a miss, else the hit's class
    scaled into (0, 1]; `delta_depth` is the change of `depth` since the previous step. Azimuth bin 0
    looks straight ahead (body +X); elevation bins run from straight down to straight up.
    """

    schema_version: Literal[2] = 2
    env_ids: I32_1D  # (N,) int32
    azimuth_bins: int = Field(gt=0)
    elevation_bins: int = Field(gt=0)
    depth: F32_3D  # (N, Az, El) float32
    semantic: F32_3D  # (N, Az, El) float32
    delta_depth: F32_3D  # (N, Az, El) float32
    step_id: int = Field(ge=0)
    timestamp: Finite
    run_id: str = ""

    @property
    def n_envs(self) -> int:
        return int(self.env_ids.shape[0])

    @model_validator(mode="after")
    def _shapes_agree(self) -> DistanceMatrix:
        want = (self.n_envs, self.azimuth_bins, self.elevation_bins)
        for name in ("depth", "semantic", "delta_depth"):
            got = getattr(self, name).shape
            if got != want:
                raise ValueError(f"{name} has shape {got}, expected (n_envs, Az, El) = {want}")
        return self


class Action(Message):
    """4-DOF body-frame velocity commands `[forward, vertical, lateral, yaw]` for N environments."""

    schema_version: Literal[2] = 2
    env_ids: I32_1D  # (N,) int32
    command: F32_2D  # (N, 4) float32, normalised to [-1, 1]
    step_id: int = Field(ge=0)
    timestamp: Finite
    policy_id: str = ""

    @model_validator(mode="after")
    def _shapes_agree(self) -> Action:
        if self.command.shape != (self.env_ids.shape[0], 4):
            raise ValueError(f"command has shape {self.command.shape}, expected (N, 4)")
        return self


class RobotPose(Message):
    """Pose of one drone in world meters and radians."""

    schema_version: Literal[1] = 1
    env_id: int = Field(ge=0)
    x: Finite
    y: Finite
    z: Finite
    roll: Finite
    pitch: Finite
    yaw: Finite
    timestamp: Finite


class StepRequest(Message):
    """Brain -> environment: apply one action per environment (or reset them) and step once."""

    schema_version: Literal[2] = 2
    request_id: str = Field(min_length=1, max_length=128)
    env_ids: I32_1D  # (N,) int32
    actions: F32_2D  # (N, 4) float32
    reset: bool = False

    @model_validator(mode="after")
    def _shapes_agree(self) -> StepRequest:
        if self.actions.shape != (self.env_ids.shape[0], 4):
            raise ValueError(f"actions has shape {self.actions.shape}, expected (N, 4)")
        return self


class StepResult(Message):
    """Environment -> brain: what one step did, per environment, and the next observation."""

    schema_version: Literal[2] = 2
    request_id: str = Field(min_length=1, max_length=128)
    step_id: int = Field(ge=0)
    env_ids: I32_1D  # (N,) int32
    reward: F32_1D  # (N,) float32
    done: BOOL_1D  # (N,) bool
    truncated: BOOL_1D  # (N,) bool
    episode_return: F32_1D  # (N,) float32, return of the episode so far (of the one that just ended on done)
    observation: DistanceMatrix | None = None

    @model_validator(mode="after")
    def _shapes_agree(self) -> StepResult:
        n = self.env_ids.shape[0]
        for name in ("reward", "done", "truncated", "episode_return"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must have shape ({n},)")
        if self.observation is not None and self.observation.n_envs != n:
            raise ValueError("observation covers a different number of environments")
        return self


class TelemetryEvent(Message):
    """One keyed numeric sample, e.g. `actor.training.sps` at a step of a run."""

    schema_version: Literal[1] = 1
    key: str = Field(min_length=1, max_length=256, pattern=r"^[A-Za-z0-9_.:/-]+$")
    value: float
    step: int = Field(ge=0)
    run_id: str = Field(default="", max_length=128)
    timestamp: Finite


class CompileJob(Message):
    """Ask a compiler worker to turn a source scene into a .gmdag file."""

    schema_version: Literal[1] = 1
    job_id: str = Field(min_length=1, max_length=128)
    source: str = Field(min_length=1)
    output: str = Field(min_length=1)
    resolution: int = Field(default=512, ge=8, le=4096)
    scale: Finite | None = None
    map_name: str | None = None
    seeds: tuple[tuple[Finite, Finite, Finite], ...] = ()
    repair: bool = False

    @model_validator(mode="after")
    def _power_of_two(self) -> CompileJob:
        if self.resolution & (self.resolution - 1):
            raise ValueError("resolution must be a power of two")
        return self


class CompileResult(Message):
    """A compiler worker's answer: the output and its stats, or a typed error."""

    schema_version: Literal[1] = 1
    job_id: str = Field(min_length=1, max_length=128)
    ok: bool
    output: str | None = None
    stats: dict[str, float] = Field(default_factory=dict)
    error_type: str | None = None
    error: str | None = None
    duration_s: Finite = 0.0
    worker_id: str = ""

    @model_validator(mode="after")
    def _consistent(self) -> CompileResult:
        if self.ok and (self.output is None or self.error is not None):
            raise ValueError("a successful result has an output and no error")
        if not self.ok and (self.error is None or self.error_type is None):
            raise ValueError("a failed result has an error_type and an error")
        return self


class ModelPromoted(Message):
    """The control plane moved an alias (e.g. `champion`) to an immutable model version."""

    schema_version: Literal[1] = 1
    alias: str = Field(min_length=1, max_length=64)
    version: str = Field(min_length=1, max_length=64)
    previous_version: str | None = None
    checkpoint: str = Field(min_length=1)
    notes: str = ""
    tags: tuple[str, ...] = ()
    timestamp: Finite


class FloorPlan(Message):
    """Top-down map of the scene an actor flies in: the signed clearance on a horizontal slice.

    `clearance` (H, W) float32 meters at height `z`, sampled at the centres of square cells of
    `cell_size` meters: cell (row i, column j) is centred at (origin_x + (j + 0.5) * cell_size,
    origin_y + (i + 0.5) * cell_size). Positive is free space, zero or less is inside geometry.
    """

    schema_version: Literal[1] = 1
    scene: str = Field(min_length=1, max_length=256)
    run_id: str = Field(default="", max_length=128)
    origin_x: Finite
    origin_y: Finite
    cell_size: Finite = Field(gt=0)
    z: Finite
    clearance: F32_2D  # (H, W) float32 meters
    timestamp: Finite

    @model_validator(mode="after")
    def _bounded(self) -> FloorPlan:
        h, w = self.clearance.shape
        if not (1 <= h <= 1024 and 1 <= w <= 1024):
            raise ValueError(f"clearance must be between 1x1 and 1024x1024 cells, got {h}x{w}")
        return self


MESSAGE_TYPES: tuple[type[Message], ...] = (
    DistanceMatrix,
    Action,
    RobotPose,
    StepRequest,
    StepResult,
    TelemetryEvent,
    CompileJob,
    CompileResult,
    ModelPromoted,
    FloorPlan,
)
