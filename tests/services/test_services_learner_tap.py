"""The learner service's tap on the training loop: transparent, rate-limited, exact samples."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any

import pytest
import torch

from navi_learner.envs.toy import ToyEnv
from navi_learner.service import FrameRepeater, TelemetryTap, TrainingMetrics, telemetry_rows
from navi_mesh import metrics


class Sink:
    def __init__(self) -> None:
        self.items: list[Any] = []

    def publish(self, message: Any) -> None:
        self.items.append(message)


def pubs() -> Any:
    return SimpleNamespace(
        observations=Sink(), actions=Sink(), telemetry=Sink(), poses=Sink(), floor_plans=Sink()
    )


def test_tap_forwards_the_env_unchanged_and_samples_exact_values() -> None:
    plain, tapped_env = ToyEnv(3, seed=5), ToyEnv(3, seed=5)
    sinks = pubs()
    tap = TelemetryTap(tapped_env, sinks, hz=1e6)
    assert (tap.n_actors, tap.device, tap.obs_shape) == (3, torch.device("cpu"), plain.obs_shape)
    assert torch.equal(plain.reset(1), tap.reset(1))
    gen = torch.Generator().manual_seed(0)
    for i in range(5):
        actions = torch.rand(3, 4, generator=gen) * 2 - 1  # (N, 4)
        a, b = plain.step(actions), tap.step(actions)
        assert torch.equal(a.obs, b.obs) and torch.equal(a.reward, b.reward)
        sample = sinks.observations.items[i]
        assert sample.step_id == (i + 1) * 3 and list(sample.env_ids) == [0]
        assert torch.equal(torch.from_numpy(sample.depth[0]), b.obs[0, 0])
        assert torch.equal(torch.from_numpy(sample.delta_depth[0]), b.obs[0, 2])
        assert torch.equal(torch.from_numpy(sinks.actions.items[i].command), actions)
        pose = sinks.poses.items[i]  # actor 0's position after the step, exactly
        position = b.info["position"][0]  # (3,) meters
        assert (pose.env_id, pose.x, pose.y, pose.z) == (0, *(float(v) for v in position))
        assert pose.timestamp == sample.timestamp


def test_tap_publishes_at_most_at_its_rate() -> None:
    sinks = pubs()
    tap = TelemetryTap(ToyEnv(2), sinks, hz=5.0)
    tap.reset()
    t0 = time.monotonic()
    steps = 0
    while time.monotonic() - t0 < 0.5:
        tap.step(torch.zeros(2, 4))
        steps += 1
    assert steps > 20
    assert 2 <= len(sinks.observations.items) <= 4  # 5 Hz over 0.5 s, plus the first sample
    assert len(sinks.actions.items) == len(sinks.observations.items)


def test_repeater_keeps_the_stream_at_rate_while_the_loop_is_busy() -> None:
    sinks = pubs()
    tap = TelemetryTap(ToyEnv(2), sinks, hz=20.0)
    tap.reset()
    repeater = FrameRepeater(tap, sinks)
    try:
        time.sleep(0.3)
        assert sinks.observations.items == []  # nothing to repeat before the first frame
        tap.step(torch.zeros(2, 4))  # one live frame, then a 1 s "PPO update" without env steps
        time.sleep(1.0)
    finally:
        repeater.close()
    frames = sinks.observations.items
    assert 10 <= len(frames) <= 22  # ~20 Hz kept up through the update (the first repeat after 1.5 periods)
    assert all(f is frames[0] for f in frames)  # the same frame: same step id and timestamp
    count = len(frames)
    time.sleep(0.2)
    assert len(sinks.observations.items) == count  # closed: nothing more
    # While the loop steps, the tap's own frames go out and the repeater stays quiet.
    sinks2 = pubs()
    tap2 = TelemetryTap(ToyEnv(2), sinks2, hz=20.0)
    tap2.reset()
    repeater2 = FrameRepeater(tap2, sinks2)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:
            tap2.step(torch.zeros(2, 4))
    finally:
        repeater2.close()
    assert repeater2.repeats <= 2 and len({f.step_id for f in sinks2.observations.items}) >= 8


def test_log_rows_become_training_telemetry_and_metrics() -> None:
    sinks = pubs()
    tap = TelemetryTap(ToyEnv(2), sinks, hz=1.0)
    on_log = TrainingMetrics(sinks, tap, torch.device("cpu"))
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
    events = {e.key: e for e in sinks.telemetry.items}
    assert events["actor.training.sps"].value == 1100.0 and events["actor.training.sps"].step == 512
    assert events["actor.training.sps"].run_id == "run-1"
    assert "actor.training.bad" not in events and "actor.training.publish_fraction" in events
    assert all(k.startswith("actor.training.") for k in events)
    assert metrics.REGISTRY.get_sample_value("navi_steps_per_second", {"mode": "train"}) == 1100.0
    assert metrics.REGISTRY.get_sample_value("navi_reward_ema") == 0.3
    assert metrics.REGISTRY.get_sample_value("navi_loss", {"name": "value_loss"}) == 0.4
    assert metrics.REGISTRY.get_sample_value("navi_steps_total", {"mode": "train"}) - before == 4 * 2
    assert metrics.REGISTRY.get_sample_value("navi_episodes_total", {"mode": "train"}) - episodes == 5.0
    rows = telemetry_rows("actor.inference", {"step": 8.0, "sps": 2.0}, "")
    assert [(e.key, e.value, e.step) for e in rows] == [("actor.inference.sps", 2.0, 8)]


def test_floor_plan_is_the_clearance_slice_of_the_scene() -> None:
    """A box room from (1, 1, 1) to (15, 15, 7) m: at z = 4 the plan's clearance is the distance to
    the nearest wall (the floor and ceiling are 3 m away), positive inside, and it spans the room."""
    import numpy as np

    from navi_compiler.dag.build import build_gmdag
    from navi_env.tracer.scene import load_corpus
    from navi_learner.service import floor_plan

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
