"""The auditor's `navi` commands: one JSON object with --json, one-line errors with exit code 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer
from typer.testing import CliRunner

from navi.commands import auditor
from navi_auditor.demos import DemoBuffer
from navi_learner.serving.checkpoint import load_checkpoint

runner = CliRunner()


def app() -> typer.Typer:
    root = typer.Typer()
    root.add_typer(auditor.app)
    return root


def write_demo(path: Path, steps: int = 40) -> None:
    rng = np.random.default_rng(0)
    buffer = DemoBuffer(scene="cli")
    for t in range(steps):
        obs = rng.random((3, 16, 8), dtype=np.float32)  # (3, Az, El)
        buffer.add(obs, rng.uniform(-1, 1, 4).astype(np.float32), np.zeros(6, np.float32), 0.1, t % 20 == 19)
    buffer.save(path)


def assert_usage_error(args: list[str], needle: str) -> None:
    result = runner.invoke(app(), args)
    assert result.exit_code == 2, result.output
    assert needle in result.output
    assert "Traceback" not in result.output


def test_bc_command_writes_a_bc_checkpoint_and_one_json_object(tmp_path: Path) -> None:
    write_demo(tmp_path / "demos" / "a.npz")
    out = tmp_path / "bc.pt"
    args = ["bc", "--demos", str(tmp_path / "demos"), "--out", str(out), "--epochs", "2", "--bptt", "10"]
    result = runner.invoke(app(), [*args, "--temporal-core", "gru", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["checkpoint"] == str(out) and summary["steps"] == 40.0
    meta = load_checkpoint(out).meta
    assert meta.training_source == "bc" and meta.temporal_core == "gru"


def test_commands_reject_bad_input_with_exit_code_2(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.npz").write_bytes(b"no")
    assert_usage_error(["bc", "--demos", str(tmp_path / "nope"), "--out", "x.pt"], "is not a folder")
    assert_usage_error(["bc", "--demos", str(tmp_path / "empty"), "--out", "x.pt"], "no .npz demonstrations")
    assert_usage_error(["bc", "--demos", str(tmp_path / "junk"), "--out", "x.pt"], "not a readable .npz")
    assert_usage_error(
        ["bc", "--demos", str(tmp_path), "--out", "x.pt", "--temporal-core", "lstm"], "unknown"
    )
    assert_usage_error(["record", "--out", str(tmp_path / "s.zarr"), "--topics", "bogus"], "unknown topic")
    assert_usage_error(["record", "--out", str(tmp_path)], "already exists")
    assert_usage_error(["replay", str(tmp_path / "missing.zarr")], "not a Zarr v3 store")
    assert_usage_error(["replay", str(tmp_path), "--rate", "0"], "--rate must be positive")
    assert_usage_error(["explore"], "exactly one of --gmdag")
    assert_usage_error(["explore", "--gmdag", "a.gmdag", "--corpus", str(tmp_path)], "exactly one of --gmdag")
    assert_usage_error(["explore", "--gmdag", str(tmp_path / "no.gmdag")], "is not a file")
    assert_usage_error(["explore", "--corpus", str(tmp_path / "empty")], "no .gmdag scenes")
