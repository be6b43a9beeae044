"""`navi bench train --profile DIR`: where one rollout and one PPO update spend the device.

torch.profiler (CPU activities, and CUDA's on a GPU) runs around one call of the training loop's two
stages, `collect` (a rollout) and `update` (the PPO update), the call after the measured ones, so the
bench's figures are those of unprofiled updates. Each stage's file (`collect-TAG.txt`, `update-TAG.txt`;
TAG `one-process` or `rank<r>`) starts with one JSON line, `busy_summary` of its kernels, then the
operator table by device time. The profiler's host cost slows the host: on several ranks a profiled
rank can starve its GPU, so read its waits from `timeline_ms`, not from these files.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

import navi_learner.ppo.train as training

STAGES = ("collect", "update")
"""The training loop's functions that are profiled (navi_learner.ppo.train)."""


def busy_summary(events: list[dict[str, Any]]) -> dict[str, float]:
    """Of a Chrome trace's events: the kernels' span, the time some kernel ran (the union of their
    intervals, streams overlapping), the kernel time summed, the NCCL kernels' share of it (ms) and
    the kernel count. All zero without kernels (a CPU run)."""
    kernels = [e for e in events if e.get("cat") == "kernel" and "dur" in e]
    if not kernels:
        return {"span_ms": 0.0, "busy_ms": 0.0, "kernel_ms": 0.0, "nccl_ms": 0.0, "kernels": 0}
    spans = sorted((float(e["ts"]), float(e["ts"]) + float(e["dur"])) for e in kernels)  # µs
    busy, (start, end) = 0.0, spans[0]
    for s, e in spans[1:]:
        if s > end:
            busy += end - start
            start, end = s, e
        else:
            end = max(end, e)
    busy += end - start
    return {
        "span_ms": (max(e for _, e in spans) - spans[0][0]) / 1e3,
        "busy_ms": busy / 1e3,
        "kernel_ms": sum(float(e["dur"]) for e in kernels) / 1e3,
        "nccl_ms": sum(float(e["dur"]) for e in kernels if "nccl" in str(e.get("name", "")).lower()) / 1e3,
        "kernels": len(kernels),
    }


def profiled(stage: str, fn: Callable[..., Any], at: int, out: Path, tag: str) -> Callable[..., Any]:
    """`fn` whose `at`-th call (1-based) runs under the profiler and writes `out/STAGE-TAG.txt`."""
    calls = 0

    def call(*args: Any, **kwargs: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls != at:
            return fn(*args, **kwargs)
        cuda = torch.cuda.is_available() and torch.cuda.is_initialized()
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        if cuda:
            torch.cuda.synchronize()
        with profile(activities=activities) as prof:
            t0 = time.perf_counter()
            result = fn(*args, **kwargs)
            if cuda:
                torch.cuda.synchronize()
            wall_ms = (time.perf_counter() - t0) * 1e3
        trace = out / f".{stage}-{tag}.trace.json"
        prof.export_chrome_trace(str(trace))
        events = json.loads(trace.read_text()).get("traceEvents", [])
        trace.unlink()
        summary = {"stage": stage, "call": at, "wall_ms": round(wall_ms, 3)} | {
            k: round(v, 3) for k, v in busy_summary(events).items()
        }
        sort = "cuda_time_total" if cuda else "cpu_time_total"
        table = prof.key_averages().table(sort_by=sort, row_limit=40, max_name_column_width=90)
        (out / f"{stage}-{tag}.txt").write_text(json.dumps(summary) + "\n" + table)
        return result

    return call


@contextmanager
def profile_stages(out: Path, at: int, tag: str) -> Iterator[None]:
    """Within the block, the `at`-th call of each of the training loop's STAGES is profiled into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    kept = {stage: getattr(training, stage) for stage in STAGES}
    try:
        for stage, fn in kept.items():
            setattr(training, stage, profiled(stage, fn, at, out, tag))
        yield
    finally:
        for stage, fn in kept.items():
            setattr(training, stage, fn)
