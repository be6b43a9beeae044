"""A small procedural corpus for the ecosystem adapters, built once per session through the `navi`
command (scenes generate + corpus build at 64³): two rooms scenes and two halls, where random flight
hits walls and pillars."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from navi.cli import build_app
from navi_env.config import EnvConfig

SMALL_VIEW = EnvConfig(azimuth_bins=16, elevation_bins=4)
"""16 x 4 rays: every adapter test and the learning tests run on it (fast on two cores)."""


@pytest.fixture(scope="session")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("ecosystem")
    runner = CliRunner()
    scenes = runner.invoke(
        build_app(),
        [
            "scenes",
            "generate",
            "--out",
            str(root / "scenes"),
            "--count",
            "4",
            "--families",
            "rooms,hall",
            "--seed",
            "2",
        ],
    )
    assert scenes.exit_code == 0, scenes.output
    built = runner.invoke(
        build_app(),
        [
            "corpus",
            "build",
            str(root / "scenes"),
            "--out",
            str(root / "corpus"),
            "--resolution",
            "64",
            "--json",
        ],
    )
    assert built.exit_code == 0, built.output
    assert json.loads(built.stdout)["scenes"] == 4
    return root / "corpus"
