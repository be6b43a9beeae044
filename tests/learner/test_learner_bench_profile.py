"""`navi bench train --profile DIR`: the kernels' busy time of a trace, and the profiled rollout and update
of a CPU run (one more update after the measured ones, the training loop left as it was)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

import navi_learner.ppo.train as training
from navi.cli import build_app
from navi_bench.profile import busy_summary, profile_stages


def test_busy_time_is_the_union_of_kernel_intervals() -> None:
    events = [
        {"cat": "kernel", "name": "gemm", "ts": 0.0, "dur": 1000.0},  # µs
        {"cat": "kernel", "name": "ncclDevKernel_AllReduce", "ts": 500.0, "dur": 1000.0},  # overlaps
        {"cat": "kernel", "name": "softmax", "ts": 3000.0, "dur": 500.0},  # after an idle millisecond
        {"cat": "cpu_op", "name": "aten::mm", "ts": 0.0, "dur": 9000.0},  # host work is not device time
    ]
    got = busy_summary(events)
    assert got == {"span_ms": 3.5, "busy_ms": 2.0, "kernel_ms": 2.5, "nccl_ms": 1.0, "kernels": 3}
    assert busy_summary(events[3:]) == {
        "span_ms": 0.0, "busy_ms": 0.0, "kernel_ms": 0.0, "nccl_ms": 0.0, "kernels": 0,
    }  # fmt: skip


def test_bench_train_profiles_the_update_after_the_measured_ones(tmp_path: Path) -> None:
    out = tmp_path / "profile"
    result = CliRunner().invoke(
        build_app(),
        [
            "bench", "train", "--env", "toy", "--actors", "8", "--rollout-length", "32", "--device", "cpu",
            "--updates", "1", "--profile", str(out), "--json",
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output[-2000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["env_train_sps"] > 0
    assert sorted(p.name for p in out.iterdir()) == ["collect-one-process.txt", "update-one-process.txt"]
    for stage in ("collect", "update"):
        first, *table = (out / f"{stage}-one-process.txt").read_text().splitlines()
        summary = json.loads(first)
        assert summary["stage"] == stage and summary["call"] == 4  # 2 warm-up, 1 measured, then this one
        assert summary["wall_ms"] > 0 and summary["kernels"] == 0  # the CPU runs no kernels
        text = "\n".join(table)
        assert "Self CPU" in text and "aten::" in text
        # each window holds its own stage: the optimizer steps in the update, never in the rollout
        assert ("Optimizer.step" in text) == (stage == "update")
    # the training loop's functions are the loop's own again
    assert training.collect.__module__ == "navi_learner.ppo.train"
    assert training.update.__name__ == "update"


def test_profile_stages_restores_the_loop_even_when_it_fails(tmp_path: Path) -> None:
    kept = (training.collect, training.update)
    with pytest.raises(RuntimeError, match="the run fails"), profile_stages(tmp_path, 1, "one-process"):
        assert training.collect is not kept[0] and training.update is not kept[1]
        raise RuntimeError("the run fails")
    assert (training.collect, training.update) == kept
