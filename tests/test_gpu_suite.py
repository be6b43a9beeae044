"""The device command runs every gpu-marked test: tests/gpu_suite.sh selects by the marker over the whole
tests/ folder, and its NAVI_GPU_ONLY pre-filter (modules without the mark's text are not imported) drops
none of them. Collected here on the CPU, where every package is installed."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def collected(gpu_only: bool) -> set[str]:
    """Node ids that `pytest -m gpu tests` collects (they skip here, but are collected)."""
    env = dict(os.environ)
    env.pop("NAVI_GPU_ONLY", None)
    if gpu_only:
        env["NAVI_GPU_ONLY"] = "1"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "--collect-only",
            "-q",
            "-p",
            "no:cacheprovider",
            "-m",
            "gpu",
            "tests",
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return {line for line in done.stdout.splitlines() if "::" in line}


def test_the_gpu_command_selects_every_gpu_marked_test_by_its_marker() -> None:
    script = (ROOT / "tests" / "gpu_suite.sh").read_text()
    (line,) = [x for x in script.splitlines() if "-m pytest" in x]
    assert re.search(r"NAVI_GPU_ONLY=1 python -m pytest .*-m gpu tests( |$)", line), line
    everything, prefiltered = collected(gpu_only=False), collected(gpu_only=True)
    assert len(everything) >= 40  # the CUDA kernels, parity, env, learner and ecosystem cases
    assert prefiltered == everything, sorted(everything ^ prefiltered)
