"""The dashboard core without Zenoh: hemisphere slicing, mode detection, freshness, the hub's queues."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from navi_auditor.hub import ClientQueue, Hub, HubConfig, snapshot_message
from navi_auditor.state import (
    DashboardConfig,
    DashboardState,
    Mode,
    forward_hemisphere,
    forward_hemisphere_ref,
    forward_indices,
    quantise,
)
from navi_contracts.models import DistanceMatrix, FloorPlan, RobotPose, TelemetryEvent


def matrix(n: int = 2, az: int = 16, el: int = 4, step: int = 0) -> DistanceMatrix:
    depth = np.random.default_rng(step).random((n, az, el), dtype=np.float32)  # (N, Az, El)
    return DistanceMatrix(
        env_ids=np.arange(n, dtype=np.int32),
        azimuth_bins=az,
        elevation_bins=el,
        depth=depth,
        semantic=depth,
        delta_depth=depth,
        step_id=step,
        timestamp=0.0,
    )


def event(key: str, value: float = 1.0, step: int = 0) -> TelemetryEvent:
    return TelemetryEvent(key=key, value=value, step=step, run_id="r", timestamp=0.0)


@pytest.mark.parametrize("az,el", [(256, 48), (16, 4), (384, 72), (8, 1)])
def test_forward_hemisphere_matches_reference(az: int, el: int) -> None:
    depth = np.random.default_rng(az).random((az, el), dtype=np.float32)  # (Az, El)
    fast = forward_hemisphere(depth)
    assert fast.shape == (el, az // 2)
    np.testing.assert_array_equal(fast, forward_hemisphere_ref(depth))


def test_forward_hemisphere_is_centred_on_straight_ahead() -> None:
    idx = forward_indices(256)
    assert idx[0] == 63 and idx[63] == 0 and idx[64] == 255 and idx[-1] == 192  # left edge ... right edge
    depth = np.ones((256, 48), np.float32)  # (Az, El)
    depth[0, 30] = 0.0  # straight ahead, above the horizon
    depth[64, 24] = 0.0  # exactly left: outside the forward half
    image = forward_hemisphere(depth)
    assert np.argwhere(image == 0.0).tolist() == [[48 - 1 - 30, 63]]
    assert quantise(np.array([[0.0, 0.01, 0.5, 1.0, np.nan, 2.0]], np.float32)).tolist() == [
        [0, 38, 217, 255, 0, 255]
    ]


def test_modes_follow_telemetry_and_fade_back_to_waiting() -> None:
    state = DashboardState(DashboardConfig(stale_after_s=2.0))
    assert state.mode(0.0) is Mode.WAITING
    state.on_observation(matrix(), now=1.0)
    assert state.mode(1.5) is Mode.OBSERVER  # a stream but no actor telemetry
    state.on_telemetry(event("actor.training.sps", 1000.0), now=2.0)
    assert state.mode(2.5) is Mode.TRAINING
    state.on_telemetry(event("actor.inference.sps", 10.0), now=3.0)
    assert state.mode(3.5) is Mode.INFERENCE  # the newest actor telemetry wins
    state.on_telemetry(event("env.step_ms", 1.0), now=5.5)
    assert state.mode(5.6) is Mode.OBSERVER  # actor telemetry went stale; other telemetry still flows
    assert state.mode(100.0) is Mode.WAITING  # everything stale: the streams disappeared
    state.on_telemetry(event("actor.training.sps", 5.0), now=101.0)
    assert state.mode(101.0) is Mode.TRAINING  # and it picks them up again


def test_snapshot_status_bar_and_charts() -> None:
    state = DashboardState(DashboardConfig(stale_after_s=5.0, history=3, max_series=2))
    snap = state.snapshot(0.0)
    assert snap.frame is None and snap.obs_age_ms is None and snap.sps is None and snap.actors is None
    state.on_observation(matrix(n=3, step=7), now=10.0, wall=0.0)  # arrives as it is stamped
    snap = state.snapshot(10.25)
    assert snap.actors == 3 and snap.frame is not None and snap.frame.step_id == 7
    assert snap.obs_age_ms == pytest.approx(250.0)
    for i in range(5):
        state.on_telemetry(event("actor.training.sps", 100.0 + i, step=i), now=10.0)
        state.on_telemetry(event("actor.training.reward_ema", -i, step=i), now=10.0)
    state.on_telemetry(event("actor.training.actors", 4096), now=10.0)
    state.on_telemetry(event("a.reward", 1.0), now=10.0)
    state.on_telemetry(event("b.reward", 1.0), now=10.0)  # over max_series: ignored
    state.on_telemetry(event("actor.training.sps", float("nan")), now=10.0)  # non-finite: ignored
    snap = state.snapshot(10.5)
    assert snap.actors == 4096 and snap.sps == 104.0
    assert snap.sps_history["actor.training.sps"] == [(2, 102.0), (3, 103.0), (4, 104.0)]
    assert set(snap.reward) == {"actor.training.reward_ema", "a.reward"}
    assert state.snapshot(20.0).frame is None  # a stale frame is not shown
    body = json.loads(snapshot_message(snap))
    assert body["mode"] == "TRAINING" and body["frame"]["width"] == 8 and body["frame"]["height"] == 4


def test_freshness_is_the_frame_age_and_repeats_do_not_look_new() -> None:
    state = DashboardState(DashboardConfig(stale_after_s=5.0))
    frame = matrix(step=3)  # stamped at wall time 0.0
    state.on_observation(frame, now=100.0, wall=0.4)  # took 400 ms to arrive
    assert state.snapshot(100.1).obs_age_ms == pytest.approx(500.0)
    state.on_observation(frame, now=101.0, wall=1.4)  # the learner repeats it during a PPO update
    snap = state.snapshot(101.5)
    assert snap.frames == 1 and snap.frame is not None and snap.frame.seq == 1
    assert snap.obs_age_ms == pytest.approx(1900.0)  # the frame's true age, not the repeat's
    state.on_observation(matrix(step=4), now=102.0, wall=0.05 + 0.0)
    assert state.snapshot(102.0).frames == 2 and state.snapshot(102.0).obs_age_ms == pytest.approx(50.0)


def test_heartbeat_keeps_mode_actors_and_sps_between_slow_updates() -> None:
    state = DashboardState(DashboardConfig(stale_after_s=5.0))
    state.on_telemetry(event("actor.training.sps", 321.0, step=64), now=0.0)
    for t in range(1, 30):  # a 30 s PPO update: only the once-a-second heartbeat arrives
        state.on_telemetry(event("actor.training.actors", 4.0, step=64), now=float(t))
    snap = state.snapshot(29.5)
    assert snap.mode is Mode.TRAINING and snap.actors == 4 and snap.sps == 321.0
    assert snap.sps_history == {"actor.training.sps": [(64, 321.0)]}  # heartbeats are not chart points
    assert state.snapshot(40.0).sps is None and state.snapshot(40.0).mode is Mode.WAITING


def test_training_charts_corpus_pose_and_floor_plan() -> None:
    state = DashboardState(DashboardConfig(stale_after_s=5.0, trail=3))
    values = {
        "collisions_per_1k": ("collisions", 3.5),
        "coverage_per_1k": ("coverage", 12.25),
        "episode_return": ("episode_return", -4.5),
        "entropy": ("entropy", 1.75),
        "value_loss": ("value_loss", 0.125),
        "reward_ema": ("reward", 0.5),
    }
    for name, (_, value) in values.items():
        state.on_telemetry(event(f"actor.training.{name}", value, step=128), now=1.0)
    corpus = {
        "corpus.scenes_ready": 3,
        "corpus.scenes_planned": 16,
        "corpus.scenes_rejected": 1,
        "corpus.ready": 0,
    }
    for key, value in corpus.items():
        state.on_telemetry(event(key, value), now=1.0)
    snap = state.snapshot(1.5)
    for name, (chart, value) in values.items():
        assert snap.charts[chart] == {f"actor.training.{name}": [(128, value)]}
    assert snap.corpus is not None and (snap.corpus.ready, snap.corpus.planned, snap.corpus.rejected) == (
        3,
        16,
        1,
    )
    assert not snap.corpus.done
    plan = FloorPlan(
        scene="room", origin_x=-1.0, origin_y=2.0, cell_size=0.5, z=1.5,
        clearance=np.array([[-0.1, 0.0, 0.5], [1.0, 2.0, 9.0]], np.float32), timestamp=0.0,
    )  # fmt: skip
    state.on_floor_plan(plan, now=1.0)
    for i in range(5):
        state.on_pose(RobotPose(env_id=0, x=i, y=2 * i, z=1.5, roll=0, pitch=0, yaw=0, timestamp=0), now=1.0)
    state.on_pose(RobotPose(env_id=1, x=99, y=99, z=0, roll=0, pitch=0, yaw=0, timestamp=0), now=1.0)
    snap = state.snapshot(1.5)
    assert snap.trail == [(2.0, 4.0), (3.0, 6.0), (4.0, 8.0)]  # the newest 3, actor 0 only
    assert snap.pose is not None and (snap.pose.x, snap.pose.y) == (4.0, 8.0)
    assert (
        snap.plan is not None
        and snap.plan.seq == 1
        and snap.plan.pixels.tolist() == [[0, 0, 112], [160, 255, 255]]
    )
    state.on_floor_plan(plan, now=2.0)  # the same plan again (sent every 5 s): nothing changes
    assert state.snapshot(2.0).plan.seq == 1 and len(state.snapshot(2.0).trail) == 3  # type: ignore[union-attr]
    state.on_floor_plan(plan.model_copy(update={"scene": "hall"}), now=3.0)  # a new scene: a new trail
    snap = state.snapshot(3.0)
    assert snap.plan is not None and snap.plan.seq == 2 and snap.plan.scene == "hall" and snap.trail == []
    body = json.loads(snapshot_message(snap))
    assert body["plan"]["scene"] == "hall" and (body["plan"]["width"], body["plan"]["height"]) == (3, 2)


def test_unusable_observations_are_counted_not_fatal() -> None:
    state = DashboardState()
    state.on_observation(matrix(az=6))  # Az not a multiple of 4: no centred forward half
    state.set_decode_errors(3)
    snap = state.snapshot()
    assert (
        (snap.bad_frames, snap.decode_errors) == (1, 3) and snap.frame is None and snap.mode is Mode.WAITING
    )


def test_client_queue_drops_oldest_and_never_blocks() -> None:
    async def scenario() -> None:
        queue = ClientQueue(3)
        for i in range(10):
            queue.put(str(i))
        assert len(queue) == 3 and queue.dropped == 7
        assert [await queue.get() for _ in range(3)] == ["7", "8", "9"]
        waiter = asyncio.create_task(queue.get())
        await asyncio.sleep(0)
        assert not waiter.done()
        queue.put("late")
        assert await asyncio.wait_for(waiter, 1.0) == "late"

    asyncio.run(scenario())


def test_a_stalled_client_does_not_stall_the_others() -> None:
    async def scenario() -> None:
        hub = Hub(HubConfig(queue_size=2))
        stalled, live = hub.connect(), hub.connect()
        received: list[str] = []

        async def reader() -> None:
            while True:
                received.append(await live.get())

        task = asyncio.create_task(reader())
        for i in range(100):
            hub.broadcast(str(i))
            await asyncio.sleep(0)

        async def last_read() -> None:
            while not received or received[-1] != "99":
                await asyncio.sleep(0)

        await asyncio.wait_for(last_read(), 60.0)
        task.cancel()
        assert received[-1] == "99" and len(received) >= 99  # the live client saw (nearly) every message
        assert len(stalled) == 2 and stalled.dropped == 98  # the stalled one kept only the newest two
        hub.disconnect(stalled)
        assert hub.clients == {live}

    asyncio.run(scenario())


def test_obstacle_collisions_share_the_collisions_chart() -> None:
    state = DashboardState(DashboardConfig(stale_after_s=5.0))
    state.on_telemetry(event("actor.training.collisions_per_1k", 2.0, step=64), now=1.0)
    state.on_telemetry(event("actor.training.obstacle_collisions_per_1k", 0.5, step=64), now=1.0)
    assert state.snapshot(1.5).charts["collisions"] == {
        "actor.training.collisions_per_1k": [(64, 2.0)],
        "actor.training.obstacle_collisions_per_1k": [(64, 0.5)],
    }
