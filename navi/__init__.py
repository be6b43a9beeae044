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


def git_commit(where: Path | None = None) -> str:
    """The commit of the checkout this package runs from (or of `where`), with "+modified" when the content
    of tracked files differs from it (what ran is then not that commit alone; file modes are not
    compared, as a copied tree may lose them), or "unknown" outside a git checkout."""
    folder = where or Path(__file__).resolve().parent

    def git(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["git", *args], cwd=folder, capture_output=True, text=True, timeout=5)

    try:
        head = git("rev-parse", "--short=12", "HEAD")
        changed = git("-c", "core.fileMode=false", "status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    commit = head.stdout.strip() if head.returncode == 0 else ""
    if not commit:
        return "unknown"
    return commit + ("+modified" if changed.returncode == 0 and changed.stdout.strip() else "")
