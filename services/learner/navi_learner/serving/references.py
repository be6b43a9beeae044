"""The checkpoints that ship with Navi (reference/: each one's JSON says how it was made): what the main
job's CPU path fine-tunes, and what a fresh run may start its weights from (TrainConfig.init_from)."""

from __future__ import annotations

from pathlib import Path

REFERENCE_DIR = Path(__file__).resolve().parents[1] / "reference"
"""Where the reference checkpoints lie, beside their JSON and README."""

REFERENCES = {"explore": REFERENCE_DIR / "mamba2.pt", "pointgoal": REFERENCE_DIR / "mamba2-pointgoal.pt"}
"""The reference checkpoint of each task."""


def checkpoint_path(spec: str) -> Path:
    """A task's name as its reference checkpoint (REFERENCES); any other spec as a path."""
    return REFERENCES.get(spec, Path(spec))
