"""The root `navi` command: groups, version, help."""

from __future__ import annotations

import subprocess
import sys

from typer.testing import CliRunner

from navi import __version__
from navi.cli import build_app

runner = CliRunner()


def test_version_prints_version_and_commit() -> None:
    result = runner.invoke(build_app(), ["--version"])
    assert result.exit_code == 0
    assert result.stdout.startswith(f"navi {__version__} (commit ")
    commit = result.stdout.split("commit ")[1].rstrip(")\n")
    assert commit == "unknown" or all(c in "0123456789abcdef" for c in commit)


def test_help_lists_the_bench_group() -> None:
    result = runner.invoke(build_app(), ["--help"])
    assert result.exit_code == 0
    assert "bench" in result.stdout


def test_console_script_runs_as_module() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "navi", "--version"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0 and out.stdout.startswith("navi ")
