"""Navi: train drones to navigate real 3D scenes with reinforcement learning.

This package holds only the `navi` command; the system lives in the workspace packages
`navi_contracts`, `navi_compiler`, `navi_env`, `navi_learner` and `navi_auditor`.
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
