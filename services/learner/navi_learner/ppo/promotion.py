"""A finished run's final checkpoint into the model registry: promoted where it beats the registry's
current model (ModelRegistry.maybe_promote); a write that fails leaves the registry as it was."""

from __future__ import annotations

import logging
from pathlib import Path

from navi_learner.ppo.runs import RunFiles
from navi_learner.serving.checkpoint import count_write_error, os_reason
from navi_learner.serving.registry import ModelRegistry

log = logging.getLogger(__name__)


def promote(registry: ModelRegistry, checkpoint: Path, run: RunFiles, temporal_core: str) -> str | None:
    """Offer `checkpoint` to the registry; returns the version it became, None where it was not promoted.

    A write that fails (a full disk) logs one error line, counts in
    navi_write_errors_total{what="registry"} and returns None: the registry keeps its last good state."""
    try:
        entry = registry.maybe_promote(
            checkpoint, notes=f"auto-promote of run {run.run_id}", tags=("rl", temporal_core)
        )
    except OSError as err:  # the registry keeps its last good state (ModelRegistry.promote)
        count_write_error("registry")
        line = f"model registry {registry.root}: {checkpoint.name} not promoted: {os_reason(err)}"
        run.logger.error(line)
        log.error(line)
        return None
    return entry.version if entry is not None else None
