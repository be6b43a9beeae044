"""Demonstration files: one .npz per flown scene, written by the explorer and read by `navi bc`.

Layout (schema version 1; T steps; docs/AUDITOR.md), all arrays indexed by step t:
    schema_version  ()              int64    1
    scene           ()              str      the scene flown (a .gmdag path or corpus scene name)
    observations    (T, 3, Az, El)  float16  what the pilot saw when choosing action t (DistanceMatrix v2)
    actions         (T, 4)          float32  [forward, vertical, lateral, yaw] in [-1, 1]
    poses           (T, 6)          float32  x, y, z (world meters), roll, pitch, yaw (radians) at observation t
    rewards         (T,)            float32  reward of applying action t
    dones           (T,)            bool     the episode ended after step t
    episode_starts  (T,)            bool     step t opens an episode: [True] + dones[:-1]
A file is written atomically (temp file in the same folder, then rename) and validated on load.
"""

from __future__ import annotations

import io
import os
import tempfile
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA_VERSION = 1
FIELDS: tuple[tuple[str, str, int], ...] = (
    ("observations", "float16", 4),
    ("actions", "float32", 2),
    ("poses", "float32", 2),
    ("rewards", "float32", 1),
    ("dones", "bool", 1),
    ("episode_starts", "bool", 1),
)
"""(name, dtype, rank) of every per-step array."""


class DemoFormatError(ValueError):
    """A file that is not a valid demonstration."""


@dataclass(frozen=True)
class Demo:
    """One validated demonstration file."""

    path: Path
    scene: str
    observations: np.ndarray  # (T, 3, Az, El) float16
    actions: np.ndarray  # (T, 4) float32
    poses: np.ndarray  # (T, 6) float32
    rewards: np.ndarray  # (T,) float32
    dones: np.ndarray  # (T,) bool
    episode_starts: np.ndarray  # (T,) bool

    @property
    def steps(self) -> int:
        return int(self.actions.shape[0])

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        c, az, el = self.observations.shape[1:]
        return (int(c), int(az), int(el))


def check_arrays(arrays: dict[str, np.ndarray]) -> None:
    """Raise DemoFormatError naming the first violation of the layout."""
    for name, dtype, rank in FIELDS:
        if name not in arrays:
            raise DemoFormatError(f"missing array {name!r}")
        value = arrays[name]
        if value.dtype != np.dtype(dtype) or value.ndim != rank:
            raise DemoFormatError(f"{name} must be {rank}-d {dtype}, got {value.ndim}-d {value.dtype}")
    steps = arrays["actions"].shape[0]
    if steps < 1:
        raise DemoFormatError("a demonstration needs at least one step")
    for name, _, _ in FIELDS:
        if arrays[name].shape[0] != steps:
            raise DemoFormatError(f"{name} has {arrays[name].shape[0]} steps, actions have {steps}")
    obs = arrays["observations"]
    if obs.shape[1] != 3 or obs.shape[2] < 4 or obs.shape[3] < 1:
        raise DemoFormatError(f"observations must be (T, 3, Az, El), got {obs.shape}")
    if arrays["actions"].shape[1] != 4 or arrays["poses"].shape[1] != 6:
        raise DemoFormatError("actions must be (T, 4) and poses (T, 6)")
    for name in ("observations", "actions", "poses", "rewards"):
        if not np.all(np.isfinite(arrays[name])):
            raise DemoFormatError(f"{name} holds non-finite values")
    if np.any(np.abs(arrays["actions"]) > 1.0):
        raise DemoFormatError("actions must lie in [-1, 1]")
    depth = obs[:, 0]  # (T, Az, El)
    if depth.min() < 0.0 or depth.max() > 1.0:
        raise DemoFormatError("observation depth (channel 0) must lie in [0, 1]")
    starts, dones = arrays["episode_starts"], arrays["dones"]
    if not starts[0] or not np.array_equal(starts[1:], dones[:-1]):
        raise DemoFormatError("episode_starts must be [True] followed by dones[:-1]")


def load_demo(path: Path) -> Demo:
    """Read and validate one .npz demonstration."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise DemoFormatError(f"{path}: not a readable .npz file: {exc}") from exc
    if "schema_version" not in arrays or int(arrays["schema_version"]) != SCHEMA_VERSION:
        raise DemoFormatError(f"{path}: schema_version must be {SCHEMA_VERSION}")
    try:
        check_arrays(arrays)
    except DemoFormatError as exc:
        raise DemoFormatError(f"{path}: {exc}") from exc
    scene = str(arrays["scene"]) if "scene" in arrays else ""
    return Demo(path, scene, *(arrays[name] for name, _, _ in FIELDS))


def load_demos(folder: Path) -> list[Demo]:
    """Every *.npz under `folder`, sorted by name, each validated; raise if there is none."""
    paths = sorted(folder.glob("*.npz"))
    if not paths:
        raise DemoFormatError(f"no .npz demonstrations in {folder}")
    demos = [load_demo(p) for p in paths]
    shapes = {d.obs_shape for d in demos}
    if len(shapes) != 1:
        raise DemoFormatError(f"demonstrations disagree on the observation shape: {sorted(shapes)}")
    return demos


def save_arrays(path: Path, scene: str, arrays: dict[str, np.ndarray]) -> Path:
    """Validate and write a demonstration atomically to `path`."""
    check_arrays(arrays)
    buffer = io.BytesIO()
    payload: dict[str, Any] = {
        "schema_version": np.int64(SCHEMA_VERSION),
        "scene": np.str_(scene),
        "created_at": np.str_(datetime.now(UTC).isoformat()),
        **arrays,
    }
    np.savez_compressed(buffer, **payload)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(buffer.getvalue())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@dataclass
class DemoBuffer:
    """Steps of one flight, accumulated on the host until `save`."""

    scene: str
    observations: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    dones: list[bool] = field(default_factory=list)

    def add(self, obs: np.ndarray, action: np.ndarray, pose: np.ndarray, reward: float, done: bool) -> None:
        """obs (3, Az, El) seen before acting, action (4,), pose (6,) at obs, reward and done of the step."""
        self.observations.append(obs.astype(np.float16))
        self.actions.append(np.clip(action, -1.0, 1.0).astype(np.float32))
        self.poses.append(pose.astype(np.float32))
        self.rewards.append(float(reward))
        self.dones.append(bool(done))

    def end_episode(self) -> None:
        """Mark the last step as the end of an episode (ESC, the step limit)."""
        if self.dones:
            self.dones[-1] = True

    def __len__(self) -> int:
        return len(self.actions)

    def arrays(self) -> dict[str, np.ndarray]:
        dones = np.array(self.dones, dtype=bool)  # (T,)
        return {
            "observations": np.stack(self.observations),  # (T, 3, Az, El) float16
            "actions": np.stack(self.actions),  # (T, 4) float32
            "poses": np.stack(self.poses),  # (T, 6) float32
            "rewards": np.array(self.rewards, dtype=np.float32),  # (T,)
            "dones": dones,  # (T,) bool
            "episode_starts": np.concatenate([[True], dones[:-1]]),  # (T,) bool
        }

    def save(self, path: Path) -> Path:
        return save_arrays(path, self.scene, self.arrays())
