"""The root `navi` command: groups, version, help."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from navi import __version__
from navi.cli import build_app

runner = CliRunner()


ROOT = Path(__file__).resolve().parents[2]


def head_commit() -> str:
    """This checkout's commit as git names it (12 hex digits), "+modified" when a tracked file differs
    from it, or "unknown" outside a git checkout."""
    done = subprocess.run(
        ["git", "rev-parse", "--short=12", "HEAD"], cwd=ROOT, capture_output=True, text=True
    )
    if done.returncode != 0:
        return "unknown"
    changed = subprocess.run(
        ["git", "-c", "core.fileMode=false", "diff", "HEAD", "--quiet"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).returncode  # 1 where a tracked file differs
    return done.stdout.strip() + ("+modified" if changed == 1 else "")


def test_version_prints_version_and_commit() -> None:
    result = runner.invoke(build_app(), ["--version"])
    assert result.exit_code == 0
    assert result.stdout == f"navi {__version__} (commit {head_commit()})\n"


def readme_commands() -> dict[str, list[str]]:
    """The README's command table: group -> the commands its row names (`navi X Y` -> X, Y)."""
    table = (ROOT / "README.md").read_text().split("## The `navi` command", 1)[1].split("\n## ", 1)[0]
    groups: dict[str, list[str]] = {}
    for row in table.splitlines():
        cells = row.replace("\\|", "/").split("|")  # `a\|b` inside a cell: alternatives
        if len(cells) < 4 or not cells[2].strip().startswith("`navi "):
            continue
        for cmd in re.findall(r"`navi ([a-z]+)(?: ([a-z/]+))?", cells[2]):
            groups.setdefault(cmd[0], []).extend(c for c in cmd[1].split("/") if c)
    return groups


def test_help_lists_every_command_the_readme_names() -> None:
    groups = readme_commands()
    assert {"compile", "train", "bench", "serve", "stack", "run"} <= set(groups)
    result = runner.invoke(build_app(), ["--help"])
    assert result.exit_code == 0
    for name, subs in groups.items():
        assert re.search(rf"│ {name} ", result.stdout), name
        if subs:
            sub_help = runner.invoke(build_app(), [name, "--help"])
            assert sub_help.exit_code == 0, (name, sub_help.output)
            for sub in subs:
                assert re.search(rf"│ {sub} ", sub_help.stdout), (name, sub)


def test_console_script_runs_as_module() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "navi", "--version"], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert out.returncode == 0 and out.stdout == f"navi {__version__} (commit {head_commit()})\n"
