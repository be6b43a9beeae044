"""`navi bench wrappers` times the raw env and every adapter over one env in one job and prints one JSON
object whose figures agree with each other (the GPU figure is taken with the same command on a GPU)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from navi.cli import build_app

pytestmark = pytest.mark.usefixtures("single_thread")


def test_bench_wrappers_prints_one_consistent_json_object(corpus: Path) -> None:
    args = ["bench", "wrappers", "--corpus", str(corpus), "--actors", "8", "--steps", "5", "--repeats", "2"]
    result = CliRunner().invoke(build_app(), [*args, "--azimuth", "16", "--elevation", "4", "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)  # the whole of stdout is one JSON object
    variants = {"raw", "raw_torchrl_copies", "gym", "gym_no_final_obs", "skrl", "torchrl"}
    assert set(out["steps_per_s"]) == set(out["ms_per_step"]) == variants
    assert set(out["overhead_pct"]) == variants - {"raw"}
    assert out["obs_shape"] == [8, 3, 16, 4] and out["device"] == "cpu"
    ms = out["ms_per_step"]
    for name in variants:
        assert out["steps_per_s"][name] == pytest.approx(8 * 1000.0 / ms[name], rel=1e-2)
    for name, pct in out["overhead_pct"].items():
        assert pct == pytest.approx(100.0 * (ms[name] - ms["raw"]) / ms["raw"], abs=0.5)
