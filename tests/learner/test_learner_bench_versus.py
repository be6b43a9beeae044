"""`navi bench train --versus OPTIONS`: the command as given and the same with OPTIONS added, each run in
a process of its own, in turn, with both medians and their ratio (a lever judged in one job)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from navi.cli import build_app
from navi_bench.train import versus_report, versus_table

ROOT = Path(__file__).resolve().parents[2]
ARGS = ["bench", "train", "--env", "toy", "--device", "cpu", "--actors", "4", "--rollout-length", "8",
        "--temporal-core", "gru", "--updates", "1"]  # fmt: skip


def run(sps: int, update_ms: float) -> dict[str, Any]:
    return {"env_train_sps": sps, "timeline_ms": {"update": update_ms}}


def test_the_report_takes_each_sides_median_and_their_ratio() -> None:
    base, variant = (
        [run(400, 9.0), run(300, 12.0), run(420, 8.9)],
        [run(440, 8.4), run(430, 8.5), run(200, 20.0)],
    )
    got = versus_report(["--no-update-graphs"], base, variant)
    assert got["versus"] == "--no-update-graphs" and got["rounds"] == 3
    assert got["median_train_sps"] == {"base": 400, "variant": 430}  # a slow run on either side is outvoted
    assert got["ratio"] == round(430 / 400, 4)
    table = versus_table(got)
    assert "round 2: base 300 SPS (update 12.00 ms), variant 430 SPS (update 8.50 ms)" in table
    assert table.endswith("median train SPS: base 400, variant 430: variant / base 1.075")
    with pytest.raises(ValueError, match="as many variant runs"):
        versus_report(["--tf32"], base, variant[:2])


def test_versus_runs_base_and_variant_in_turn_each_in_its_own_process(tmp_path: Path) -> None:
    paths = [
        ROOT,
        *(ROOT / p for p in ("services/compiler", "services/env", "services/learner", "benchmarks")),
    ]
    path = os.pathsep.join([*map(str, paths), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}  # the runs are fresh interpreters
    cmd = [sys.executable, "-m", "navi", *ARGS, "--versus", "--max-minibatch 8", "--rounds", "1", "--json",
           "--record", str(tmp_path / "results")]  # fmt: skip
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout)
    assert report["versus"] == "--max-minibatch 8" and report["rounds"] == 1
    (base,), (variant,) = report["base"], report["variant"]
    assert base["max_minibatch"] == 8192 and variant["max_minibatch"] == 8  # the variant ran with its options
    assert base["actors"] == variant["actors"] == 4  # and with the base's
    assert report["median_train_sps"] == {"base": base["env_train_sps"], "variant": variant["env_train_sps"]}
    assert report["ratio"] == round(variant["env_train_sps"] / base["env_train_sps"], 4)
    assert f"round 1: base {base['env_train_sps']:,} SPS" in done.stderr
    (record_file,) = (tmp_path / "results").glob("*.jsonl")  # one record, the comparison, from the parent
    (row,) = [json.loads(line) for line in record_file.read_text().splitlines()]
    assert row["bench"] == "train" and "--versus" in row["command"] and row["ratio"] == report["ratio"]


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        (["--versus", "--tf32", "--nproc", "2"], "leave out --nproc and --profile"),
        (["--versus", "--tf32", "--profile", "p"], "leave out --nproc and --profile"),
        (["--versus", " "], "--versus needs the options"),
        (["--rounds", "3"], "name --versus too"),
    ],
)
def test_versus_refuses_what_it_cannot_compare(extra: list[str], said: str) -> None:
    result = CliRunner().invoke(build_app(), [*ARGS, *extra])
    assert result.exit_code == 2 and said in result.output, result.output
