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


def build_corpus(root: Path, seed: int) -> Path:
    """Four rooms and halls scenes of corpus seed `seed`, built at 64³ through the `navi` command."""
    runner = CliRunner()
    generate = [
        "scenes",
        "generate",
        "--out",
        str(root / "scenes"),
        "--count",
        "4",
        "--families",
        "rooms,hall",
    ]
    scenes = runner.invoke(build_app(), [*generate, "--seed", str(seed)])
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


@pytest.fixture(scope="session")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_corpus(tmp_path_factory.mktemp("ecosystem"), seed=2)


@pytest.fixture(scope="session")
def unseen_corpus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four other rooms and halls scenes (corpus seed 3), never trained on."""
    return build_corpus(tmp_path_factory.mktemp("ecosystem-unseen"), seed=3)
