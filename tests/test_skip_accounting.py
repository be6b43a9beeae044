"""The suite says what it skipped and why, and under NAVI_ALLOWED_SKIPS (CI) a skip for any other reason
fails the run. Checked on a small suite that uses this repository's conftest.py."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUITE = """
import pytest

@pytest.mark.gpu
def test_kernel():
    pass

def test_needs_a_browser():
    pytest.skip("chromium is not installed")

def test_plain():
    assert True
"""


def run_suite(tmp_path: Path, allowed: str | None) -> subprocess.CompletedProcess[str]:
    shutil.copy(ROOT / "tests" / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_small.py").write_text(SUITE)
    env = {k: v for k, v in os.environ.items() if k not in ("NAVI_ALLOWED_SKIPS", "NAVI_GPU_ONLY")}
    env["CUDA_VISIBLE_DEVICES"] = ""  # the gpu case skips for its one allowed reason, GPU host or not
    if allowed is not None:
        env["NAVI_ALLOWED_SKIPS"] = allowed
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", str(tmp_path)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_skip_table_counts_each_reason(tmp_path: Path) -> None:
    done = run_suite(tmp_path, None)
    assert done.returncode == 0, done.stdout
    assert "skips by reason" in done.stdout
    assert "    1  needs a CUDA device" in done.stdout
    assert "    1  chromium is not installed" in done.stdout


def test_a_skip_ci_does_not_allow_fails_the_run(tmp_path: Path) -> None:
    done = run_suite(tmp_path, "needs a CUDA device")
    assert done.returncode == 1, done.stdout
    assert "UNEXPECTED SKIP (1): chromium is not installed" in done.stdout
    assert "1 passed, 2 skipped" in done.stdout
    allowed = run_suite(tmp_path, "needs a CUDA device|chromium is not installed")
    assert allowed.returncode == 0, allowed.stdout
