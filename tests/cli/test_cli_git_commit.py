"""Records name the commit that ran (and say when tracked files differed from it) and the host CPU."""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
from pathlib import Path

import pytest

from navi import git_commit
from navi.commands.common import cpu_model

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def _git(folder: Path, *args: str) -> str:
    env = os.environ | {
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    out = subprocess.run(["git", *args], cwd=folder, capture_output=True, text=True, check=True, env=env)
    return out.stdout.strip()


@needs_git
def test_a_modified_checkout_is_marked_and_an_untracked_file_is_not(tmp_path: Path) -> None:
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.txt").write_text("one\n")
    _git(tmp_path, "add", "a.txt")
    _git(tmp_path, "commit", "-qm", "first")
    head = _git(tmp_path, "rev-parse", "--short=12", "HEAD")
    assert git_commit(tmp_path) == head
    (tmp_path / "notes.txt").write_text("not tracked\n")
    assert git_commit(tmp_path) == head
    (tmp_path / "a.txt").chmod(0o755)  # a copied tree may change modes: not a change of what runs
    assert git_commit(tmp_path) == head
    (tmp_path / "a.txt").write_text("two\n")
    assert git_commit(tmp_path) == head + "+modified"


def test_outside_a_checkout_the_commit_is_unknown(tmp_path: Path) -> None:
    assert git_commit(tmp_path) == "unknown"


def test_records_name_the_host_cpu_from_its_first_model_name() -> None:
    info = (
        "processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Platinum 8480+\n\n"
        "processor\t: 1\nmodel name\t: Intel(R) Xeon(R) Platinum 8480+\n"
    )
    assert cpu_model(info) == "Intel(R) Xeon(R) Platinum 8480+"
    assert cpu_model("processor\t: 0\nmodel name\t:   \n") == (platform.processor() or "unknown")
    assert cpu_model() != ""  # this host's, whatever it is
