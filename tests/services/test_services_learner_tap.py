"""The learner service's tap on the training loop, through a real Zenoh router to a real subscriber:
transparent, rate-limited, exact samples.

The tap and the frame repeater read `time.monotonic` of navi_learner.service; the tests set that clock
(`Clock`), so every rate is checked exactly and no check depends on how fast this machine runs. Each
sample is awaited at the subscriber before the next is made (the streams are drop-oldest queues of 2).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import torch
from services_testlib import client_session, loopback_router, matched, wait_for

import navi_learner.service as learner_service
from navi_contracts.models import Message
from navi_contracts.topics import ACTIONS, FLOOR_PLAN, OBSERVATIONS, POSES, TELEMETRY
from navi_learner.envs.toy import ToyEnv
from navi_learner.service import (
    FrameRepeater,
    MeshPublishers,
    TelemetryTap,
    TrainingMetrics,
    telemetry_rows,
)
from navi_mesh import metrics
from navi_mesh.pubsub import subscribe

pytestmark = pytest.mark.integration

STREAMS = (OBSERVATIONS, ACTIONS, POSES, TELEMETRY, FLOOR_PLAN)
WAIT_S = 60.0
"""Bounds a hang only: each sample crosses loopback in milliseconds."""


class Clock:
    """`time` of navi_learner.service with a monotonic clock the test sets; it counts the reads of each
    thread (the frame repeater reads it once per period after the first frame)."""

    def __init__(self) -> None:
        self.now = 0.0
        self.reads: collections.Counter[str] = collections.Counter()

    def monotonic(self) -> float:
        self.reads[threading.current_thread().name] += 1
        return self.now

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


@dataclass
class Mesh:
    pubs: MeshPublishers
    got: dict[str, list[Message]]
    clock: Clock

    def received(self, n: int, topic: str = OBSERVATIONS.key) -> list[Any]:
        """Wait until the subscriber holds n messages of `topic`; returns them."""
        wait_for(lambda: len(self.got[topic]) >= n, WAIT_S, f"{n} messages on {topic}", poll_s=0.005)
        return self.got[topic]


@pytest.fixture
def mesh(monkeypatch: pytest.MonkeyPatch) -> Iterator[Mesh]:
    """The learner's publishers on one client session, a subscriber to each stream on another, both on a
    router in this process; every stream matched before the test publishes."""
    clock = Clock()
    monkeypatch.setattr(learner_service, "time", clock)
    with loopback_router() as endpoint:
        learner, listener = client_session(endpoint), client_session(endpoint)
        got: dict[str, list[Message]] = {t.key: [] for t in STREAMS}
        subs = [subscribe(listener, t, got[t.key].append) for t in STREAMS]
        pubs = MeshPublishers(learner, telemetry_capacity=256)
        for topic in STREAMS:
            matched(learner, topic.key)
        try:
            yield Mesh(pubs, got, clock)
        finally:
            pubs.close()
            for sub in subs:
                sub.undeclare()
            learner.close()
            listener.close()


def test_tap_forwards_the_env_unchanged_and_samples_exact_values(mesh: Mesh) -> None:
    plain, tapped_env = ToyEnv(3, seed=5), ToyEnv(3, seed=5)
    tap = TelemetryTap(tapped_env, mesh.pubs, hz=1.0)
    assert (tap.n_actors, tap.device, tap.obs_shape) == (3, torch.device("cpu"), plain.obs_shape)
    assert torch.equal(plain.reset(1), tap.reset(1))
    gen = torch.Generator().manual_seed(0)
    for i in range(5):
        mesh.clock.now = float(i)  # a period (1 s) after the last sample: each step is sampled
        actions = torch.rand(3, 4, generator=gen) * 2 - 1  # (N, 4)
        a, b = plain.step(actions), tap.step(actions)
        assert torch.equal(a.obs, b.obs) and torch.equal(a.reward, b.reward)
        sample = mesh.received(i + 1)[i]
        assert sample.step_id == (i + 1) * 3 and list(sample.env_ids) == [0]
        assert torch.equal(torch.tensor(sample.depth[0]), b.obs[0, 0])
        assert torch.equal(torch.tensor(sample.delta_depth[0]), b.obs[0, 2])
        action = mesh.received(i + 1, ACTIONS.key)[i]
        assert action.step_id == sample.step_id and torch.equal(torch.tensor(action.command), actions)
        pose = mesh.received(i + 1, POSES.key)[i]  # actor 0's position after the step, exactly
        position = b.info["position"][0]  # (3,) meters
        assert (pose.env_id, pose.x, pose.y, pose.z) == (0, *(float(v) for v in position))
        assert pose.timestamp == sample.timestamp


def test_tap_publishes_at_most_at_its_rate(mesh: Mesh) -> None:
    """4 Hz over 4 s of 16 steps a second: a sample on every 4th step, the first step's included."""
    tap = TelemetryTap(ToyEnv(2), mesh.pubs, hz=4.0)
    tap.reset()
    for i in range(64):
        mesh.clock.now = i / 16  # exact in binary: the period (0.25 s) is 4 steps
        tap.step(torch.zeros(2, 4))
        mesh.received(i // 4 + 1)
    assert mesh.pubs.observations.flush(WAIT_S) and mesh.pubs.actions.flush(WAIT_S)
    sampled = [(i + 1) * 2 for i in range(0, 64, 4)]  # step ids: 2 actors a step
    assert mesh.pubs.observations.sent == len(sampled) == 16
    assert [f.step_id for f in mesh.received(16)] == sampled
    assert [a.step_id for a in mesh.received(16, ACTIONS.key)] == sampled
    assert mesh.pubs.observations.dropped == 0


def test_repeater_keeps_the_stream_at_rate_while_the_loop_is_busy(mesh: Mesh) -> None:
    tap = TelemetryTap(ToyEnv(2), mesh.pubs, hz=20.0)
    tap.reset()
    repeater = FrameRepeater(tap, mesh.pubs)
    opened = time.monotonic()  # the real clock: the repeater waits a real period between checks
    try:
        tap.step(torch.zeros(2, 4))  # one live frame at t = 0 ...
        live = mesh.received(1)[0]
        mesh.clock.now = 0.07  # ... a gap under 1.5 periods (0.075 s) is jitter: nothing repeated
        wait_for(lambda: mesh.clock.reads["navi-frame-repeater"] >= 3, WAIT_S, "three checks of the gap")
        assert repeater.repeats == 0
        mesh.clock.now = 1.0  # ... then a 1 s "PPO update" without env steps: repeats, once per period
        mesh.received(6)
    finally:
        repeater.close()
    closed = time.monotonic()
    assert mesh.pubs.observations.flush(WAIT_S)
    frames = mesh.received(1 + repeater.repeats)
    assert len(frames) == 1 + repeater.repeats  # closed: nothing more
    assert repeater.repeats <= (closed - opened) / tap.period + 1  # at most one a period
    # the same frame: same step id and timestamp (a dashboard shows the frame's true age)
    assert live.step_id == 2 and all((f.step_id, f.timestamp) == (2, live.timestamp) for f in frames)


def test_repeater_stays_quiet_while_the_loop_steps(mesh: Mesh) -> None:
    tap = TelemetryTap(ToyEnv(2), mesh.pubs, hz=16.0)
    tap.reset()
    repeater = FrameRepeater(tap, mesh.pubs)
    steps = 0
    try:
        # a step every period (exact in binary): each is sampled and goes out; the gap never reaches
        # 1.5 periods, however many times the repeater looks
        while steps < 8 or mesh.clock.reads["navi-frame-repeater"] < 5:
            mesh.clock.now = steps / 16
            tap.step(torch.zeros(2, 4))
            steps += 1
            mesh.received(steps)
    finally:
        repeater.close()
    assert repeater.repeats == 0
    assert [f.step_id for f in mesh.received(steps)] == [2 * (i + 1) for i in range(steps)]


def test_log_rows_become_training_telemetry_and_metrics(mesh: Mesh) -> None:
    tap = TelemetryTap(ToyEnv(2), mesh.pubs, hz=1.0)
    on_log = TrainingMetrics(mesh.pubs, tap, torch.device("cpu"))
    before = metrics.REGISTRY.get_sample_value("navi_steps_total", {"mode": "train"}) or 0.0
    episodes = metrics.REGISTRY.get_sample_value("navi_episodes_total", {"mode": "train"}) or 0.0
    tap.reset()
    for _ in range(4):
        tap.step(torch.zeros(2, 4))
    on_log(
        "run-1",
        {
            "step": 256.0,
            "sps": 1000.0,
            "reward_ema": 0.25,
            "policy_loss": -0.1,
            "value_loss": 0.5,
            "episode_count": 3.0,
            "episodes": 3.0,
            "bad": float("nan"),
        },
    )
    on_log(
        "run-1",
        {
            "step": 512.0,
            "sps": 1100.0,
            "reward_ema": 0.3,
            "policy_loss": -0.2,
            "value_loss": 0.4,
            "episode_count": 5.0,
            "episodes": 2.0,
        },
    )
    assert mesh.pubs.telemetry.flush(WAIT_S) and mesh.pubs.telemetry.dropped == 0
    sent = mesh.pubs.telemetry.sent
    assert sent == 2 * 7  # per row: its six finite values besides the step, and publish_fraction
    events = {e.key: e for e in mesh.received(sent, TELEMETRY.key)}
    assert events["actor.training.sps"].value == 1100.0 and events["actor.training.sps"].step == 512
    assert events["actor.training.sps"].run_id == "run-1"
    assert "actor.training.bad" not in events and "actor.training.publish_fraction" in events
    assert all(k.startswith("actor.training.") for k in events)
    assert metrics.REGISTRY.get_sample_value("navi_steps_per_second", {"mode": "train"}) == 1100.0
    assert metrics.REGISTRY.get_sample_value("navi_reward_ema") == 0.3
    assert metrics.REGISTRY.get_sample_value("navi_loss", {"name": "value_loss"}) == 0.4
    assert (metrics.REGISTRY.get_sample_value("navi_steps_total", {"mode": "train"}) or 0.0) - before == 4 * 2
    assert (
        metrics.REGISTRY.get_sample_value("navi_episodes_total", {"mode": "train"}) or 0.0
    ) - episodes == 5.0
    rows = telemetry_rows("actor.inference", {"step": 8.0, "sps": 2.0}, "")
    assert [(e.key, e.value, e.step) for e in rows] == [("actor.inference.sps", 2.0, 8)]


def test_floor_plan_is_the_clearance_slice_of_the_scene() -> None:
    """A box room from (1, 1, 1) to (15, 15, 7) m: at z = 4 the plan's clearance is the distance to
    the nearest wall (the floor and ceiling are 3 m away), positive inside, and it spans the room."""
    import numpy as np

    from navi_compiler.dag.build import build_gmdag
    from navi_env.tracer.scene import load_corpus
    from navi_learner.service.floor_plan import floor_plan

    res, voxel = 32, 0.5
    i = np.arange(res + 1, dtype=np.float64) * voxel
    p = np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)  # (R+1, R+1, R+1, 3) meters
    lo, hi = np.array([1.0, 1.0, 1.0]), np.array([15.0, 15.0, 7.0])
    q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)  # > 0 outside
    g = build_gmdag((-box / voxel).astype(np.float32), origin=(0.0, 0.0, 0.0), voxel_size=voxel,
                    spawns=np.array([[8.0, 8.0, 4.0]]), bounds=(tuple(lo), tuple(hi)))  # fmt: skip
    plan = floor_plan(load_corpus([g], "cpu"), 0, 4.0, cells=28, run_id="r")
    assert plan.clearance.shape == (28, 28) and plan.cell_size == pytest.approx(0.5)
    assert (plan.origin_x, plan.origin_y, plan.z, plan.run_id) == (1.0, 1.0, 4.0, "r")
    centres = 1.0 + (np.arange(28) + 0.5) * 0.5  # (28,) cell centres, meters
    gx, gy = np.meshgrid(centres, centres)  # (28, 28), row = y
    expected = np.minimum(np.minimum(gx - 1.0, 15.0 - gx), np.minimum(gy - 1.0, 15.0 - gy))
    expected = np.minimum(expected, 3.0)  # floor and ceiling
    near = expected <= 1.0  # within the field's exact band of a wall
    np.testing.assert_allclose(plan.clearance[near], expected[near], atol=0.3)  # half a voxel
    assert (plan.clearance <= expected + 0.3).all()  # farther away the field stores a lower bound
    assert (plan.clearance > 0).all() and near.sum() > 100
