"""Navi: train drones to navigate real 3D scenes with reinforcement learning.

The top layer: the `navi` command (cli.py over the groups in commands/) and the wiring that starts
several services together (stack.py, `navi stack`). The system itself lives in the workspace packages
below it, each importing only those under it: navi_contracts <- navi_mesh <- navi_compiler <- navi_env
<- navi_learner <- navi_auditor <- navi (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

__version__ = "0.1.0"


def git_commit() -> str:
    """The commit of the checkout this package runs from, or "unknown" outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown"
