"""Building wire messages from the core's tensors (host copies taken at the publishing rate only)."""

from __future__ import annotations

import time

import numpy as np

from navi_contracts.models import Action, DistanceMatrix, TelemetryEvent


def distance_matrix(obs: np.ndarray, env_ids: np.ndarray, step_id: int, run_id: str = "") -> DistanceMatrix:
    """obs (K, 3, Az, El) float32 (channels depth, semantic, delta depth) of the actors env_ids (K,)."""
    obs = np.asarray(obs, dtype=np.float32)  # (K, 3, Az, El)
    return DistanceMatrix(
        env_ids=np.asarray(env_ids, dtype=np.int32),  # (K,)
        azimuth_bins=int(obs.shape[2]),
        elevation_bins=int(obs.shape[3]),
        depth=np.ascontiguousarray(obs[:, 0]),  # (K, Az, El)
        semantic=np.ascontiguousarray(obs[:, 1]),  # (K, Az, El)
        delta_depth=np.ascontiguousarray(obs[:, 2]),  # (K, Az, El)
        step_id=int(step_id),
        timestamp=time.time(),
        run_id=run_id,
    )


def action_message(actions: np.ndarray, step_id: int, policy_id: str = "") -> Action:
    """actions (N, 4) float32 of actors 0..N-1."""
    command = np.ascontiguousarray(actions, dtype=np.float32)  # (N, 4)
    return Action(
        env_ids=np.arange(command.shape[0], dtype=np.int32),  # (N,)
        command=command,
        step_id=int(step_id),
        timestamp=time.time(),
        policy_id=policy_id,
    )


def telemetry(key: str, value: float, step: int, run_id: str = "") -> TelemetryEvent:
    """One keyed numeric sample stamped now."""
    return TelemetryEvent(key=key, value=float(value), step=int(step), run_id=run_id, timestamp=time.time())
