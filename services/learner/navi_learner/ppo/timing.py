"""Where a run's time goes: the time per stage of a training step (StageTimers) and the training clock
that SPS and the time budget read (Clock)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch

STAGES = ("env", "forward", "learn")
"""The stages a step's time is split into (they do not overlap)."""
TIMED = (*STAGES, "sync")
"""What StageTimers reports: the stages, and "sync", the time a data-parallel run waits for its collectives
(ppo.dist.Sync): mostly the rollout's per-step normaliser sums and each minibatch's normalisation and
gradient buckets, which lie within forward and learn, plus a few per update and per log line. A stage
leaves out the time of the stages opened within it, so forward and learn do not count their sync and the
four never overlap: per rank, a timeline of the step. Timed by CUDA events, a wait is the time the
device's stream stalls on the collective: the other ranks' arrival plus the transfer not yet done."""


class StageTimers:
    """Time per stage, read as ms per env step once per log line. A stage opened within another (sync
    within forward or learn) counts for itself alone: the outer one leaves its time out.

    Without `sync` (training's default) a stage's time is the host's wall time between its boundaries; on
    CUDA that is mostly launch time, since kernels run on after the host moves on. With `sync` on CUDA
    (benchmarks) a pair of CUDA events brackets every stage on the current stream and the GPU time
    between them is read at the log line, with one wait for the last event: exact stage times with no
    host wait inside the loop, so that timing them does not slow the run it measures."""

    def __init__(self, sync: bool) -> None:
        self.sync = sync
        self.seconds = dict.fromkeys(TIMED, 0.0)
        self.open: list[str] = []  # the stages entered and not yet left, innermost last
        # recorded, not yet read: (stage, the stage it lies within or "", start, end)
        self.spans: list[tuple[str, str, torch.cuda.Event, torch.cuda.Event]] = []
        self.pool: list[torch.cuda.Event] = []  # events already read, recorded again (allocated once)

    def _event(self) -> torch.cuda.Event:
        event = self.pool.pop() if self.pool else torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def _add(self, stage: str, outer: str, seconds: float) -> None:
        self.seconds[stage] += seconds
        if outer:
            self.seconds[outer] -= seconds

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        outer = self.open[-1] if self.open else ""
        self.open.append(stage)
        try:
            if self.sync:
                start = self._event()
                yield
                self.spans.append((stage, outer, start, self._event()))
            else:
                t0 = time.perf_counter()
                yield
                self._add(stage, outer, time.perf_counter() - t0)
        finally:
            self.open.pop()

    def read(self, steps: int) -> dict[str, float]:
        """ms per env step (all actors) per stage since the last read, then clear."""
        if self.spans:
            self.spans[-1][3].synchronize()
            for stage, outer, start, end in self.spans:
                self._add(stage, outer, start.elapsed_time(end) / 1000.0)
                self.pool += (start, end)
            self.spans.clear()
        out = {f"ms_{k}": 1000.0 * v / max(steps, 1) for k, v in self.seconds.items()}
        self.seconds = dict.fromkeys(TIMED, 0.0)
        return out


class Clock:
    """Training time (wall time less what the monitor took) and the window the SPS of a log line covers."""

    def __init__(self) -> None:
        self.t_start = self.t_window = time.perf_counter()
        self.paused = 0.0  # seconds spent in the monitor, not training
        self.steps_window = 0

    def train_s(self) -> float:
        return time.perf_counter() - self.t_start - self.paused

    def pause(self, seconds: float) -> None:
        """Leave `seconds` out of training time and out of the SPS window."""
        self.paused += seconds
        self.t_window += seconds

    def window_sps(self) -> float:
        """Env steps per second since the last call; starts a new window."""
        now = time.perf_counter()
        sps = self.steps_window / (now - self.t_window)
        self.t_window, self.steps_window = now, 0
        return sps
