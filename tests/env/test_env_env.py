"""SdfDagEnv end to end on small analytic scenes: layout, frames, contact, episodes, determinism."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import Gmdag
from navi_env.config import EnvConfig, ObstacleConfig, SensorConfig
from navi_env.sim import env as env_module
from navi_env.sim.env import INFO_KEYS, SdfDagEnv
from navi_env.sim.rewards import TERMS
from navi_env.tracer.scene import SceneCorpus, load_corpus

RES, VOXEL = 32, 0.5  # a 16 m cube


def lattice_points() -> np.ndarray:
    i = np.arange(RES + 1, dtype=np.float64) * VOXEL
    return np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)  # (R+1, R+1, R+1, 3) meters


def room_gmdag(
    lo: tuple[float, float, float] = (1.0, 1.0, 1.0),
    hi: tuple[float, float, float] = (15.0, 15.0, 7.0),
    spawn: tuple[float, float, float] = (8.0, 8.0, 4.0),
) -> Gmdag:
    """The free inside of a box room (walls everywhere else), distances in voxels."""
    p = lattice_points()
    c, h = (np.array(lo) + np.array(hi)) / 2, (np.array(hi) - np.array(lo)) / 2
    q = np.abs(p - c) - h
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)  # >0 outside the room
    return build_gmdag(
        (-box / VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=VOXEL,
        spawns=np.array([spawn]),
        bounds=(lo, hi),
    )


def open_gmdag() -> Gmdag:
    """A small ball in open space: a view from anywhere else is mostly void."""
    p = lattice_points()
    d = np.linalg.norm(p - 8.0, axis=-1) - 1.0
    return build_gmdag(
        (d / VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=VOXEL,
        bounds=((0.5, 0.5, 0.5), (15.5, 15.5, 15.5)),
    )


@pytest.fixture(scope="module")
def room() -> SceneCorpus:
    return load_corpus([room_gmdag()], "cpu")


SMALL = EnvConfig(azimuth_bins=32, elevation_bins=8)


def test_observation_layout_wall_ahead_is_bin_zero(room: SceneCorpus) -> None:
    env = SdfDagEnv(room, 2, "cpu", SMALL, spawns=[torch.tensor([[8.0, 8.0, 4.0]])])
    env.reset(seed=0)
    env.position.copy_(torch.tensor([[12.0, 10.0, 4.0], [10.0, 12.0, 4.0]]))
    env.yaw.copy_(torch.tensor([0.0, math.pi / 2]))  # actor 1 faces +Y: its nearest wall is ahead too
    env.safe_distance.copy_(torch.tensor([3.0, 3.0]))
    env.clearance.copy_(torch.tensor([3.0, 3.0]))
    out = env.step(torch.zeros(2, 4))
    az, el = SMALL.azimuth_bins, SMALL.elevation_bins
    assert out.obs.shape == (2, 3, az, el) and env.obs_shape == (3, az, el)
    e = el // 2  # the bin just above the horizon (+11.25 degrees)
    ring = out.obs[:, 0, :, e] * SMALL.horizon * math.cos(math.radians(11.25))  # (2, Az) horizontal distance
    for n in range(2):
        assert int(ring[n].argmin()) == 0  # the nearest wall lands in azimuth bin 0
        assert abs(float(ring[n, 0]) - 3.0) < 0.15
    quarter = [0, az // 4, az // 2, 3 * az // 4]  # ahead, left, behind, right
    expected = torch.tensor([[3.0, 5.0, 11.0, 9.0], [3.0, 9.0, 11.0, 5.0]])  # actor 1 is turned to the left
    assert torch.allclose(ring[:, quarter], expected, atol=0.1)
    assert torch.all(out.obs[:, 1] >= 0.5)  # a closed room: every ray hits


def test_drone_flying_into_walls_never_penetrates_and_never_dies(room: SceneCorpus) -> None:
    cfg = EnvConfig(azimuth_bins=16, elevation_bins=4)
    env = SdfDagEnv(
        room, 8, "cpu", cfg, spawns=[torch.tensor([[8.0, 8.0, 4.0], [5.0, 5.0, 2.0], [12.0, 9.0, 6.0]])]
    )
    env.reset(seed=3)
    actions = torch.tensor([[1.0, 0.3, 0.2, 0.0]] * 4 + [[1.0, -1.0, 0.0, 0.1]] * 4)
    contacts = 0
    for _ in range(60):
        out = env.step(actions)
        assert not out.done.any() and not out.truncated.any()
        assert float(out.info["clearance"].min()) >= cfg.drone_radius - 1e-4
        p = out.info["position"]
        assert torch.all((p >= torch.tensor([1.0, 1.0, 1.0])) & (p <= torch.tensor([15.0, 15.0, 7.0])))
        contacts += int(out.info["collision"].sum())
        assert torch.all(out.reward_terms["collision"][out.info["collision"]] < 0)
    assert contacts > 0


def test_step_out_terms_and_info(room: SceneCorpus) -> None:
    env = SdfDagEnv(room, 3, "cpu", SMALL)
    env.reset(seed=1)
    out = env.step(torch.rand(3, 4) * 2 - 1)
    assert tuple(out.reward_terms) == TERMS
    assert torch.allclose(sum(out.reward_terms.values()), out.reward)
    assert set(out.info) == set(INFO_KEYS)
    assert out.info["position"].shape == (3, 3) and out.info["clearance"].shape == (3,)
    assert env.bytes_per_actor() > 4 * 3 * SMALL.rays


def rollout(env: SdfDagEnv, seed: int, steps: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(99)
    frames = [env.reset(seed=seed).clone()]
    for _ in range(steps):
        out = env.step(torch.rand(env.n_actors, 4, generator=g) * 2 - 1)
        frames += [out.obs.clone(), out.reward.clone(), out.info["position"].clone()]
    return frames


def test_seeded_determinism(room: SceneCorpus) -> None:
    cfg = EnvConfig(
        azimuth_bins=16,
        elevation_bins=4,
        max_steps_per_episode=7,
        sensor=SensorConfig(range_noise_std=0.05, dropout=0.02),
    )
    spawns = [torch.tensor([[8.0, 8.0, 4.0], [5.0, 5.0, 2.0], [12.0, 9.0, 6.0]])]
    a = rollout(SdfDagEnv(room, 4, "cpu", cfg, spawns=spawns), 5, 15)
    b = rollout(SdfDagEnv(room, 4, "cpu", cfg, spawns=spawns), 5, 15)
    c = rollout(SdfDagEnv(room, 4, "cpu", cfg, spawns=spawns), 6, 15)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(torch.equal(x, y) for x, y in zip(a, c, strict=True))


@pytest.mark.parametrize(("obstacles", "squad"), [(0, 0), (3, 0), (2, 2)])
def test_fused_stages_compile_whole_and_change_nothing(
    room: SceneCorpus, monkeypatch: pytest.MonkeyPatch, obstacles: int, squad: int
) -> None:
    """The stages the env compiles on CUDA trace into whole graphs (fullgraph: no break, the
    distance samples as navi::sample_distance ops) that reproduce the eager rollout bit for bit; the
    "aot_eager" backend runs those graphs with the eager kernels (inductor's own: test_env_gpu.py)."""
    cfg = EnvConfig(
        azimuth_bins=16,
        elevation_bins=4,
        max_steps_per_episode=6,
        episodes_per_scene=1,
        obstacles=ObstacleConfig(count=obstacles, squad=squad),
    )
    corpus = load_corpus([room_gmdag(), room_gmdag(spawn=(4.0, 4.0, 3.0))], "cpu")
    spawns = [
        torch.tensor([[8.0, 8.0, 4.0], [5.0, 5.0, 2.0]]),
        torch.tensor([[4.0, 4.0, 3.0], [12.0, 9.0, 6.0]]),
    ]
    eager = rollout(SdfDagEnv(corpus, 4, "cpu", cfg, spawns=spawns), 3, 14)
    monkeypatch.setattr(env_module, "_eager", lambda fn: env_module.fused(fn, "aot_eager", fullgraph=True))
    compiled = rollout(SdfDagEnv(corpus, 4, "cpu", cfg, spawns=spawns), 3, 14)
    assert all(torch.equal(x, y) for x, y in zip(eager, compiled, strict=True))


def test_two_observation_buffers_change_no_value_and_keep_the_last_frame(room: SceneCorpus) -> None:
    """obs_buffers=2: the same observations, rewards and positions as one buffer, bit for bit (the delta
    channel reads the previous frame from the other buffer); each step's observation is still intact
    after the next step, as previous_obs."""
    base = EnvConfig(azimuth_bins=16, elevation_bins=4, max_steps_per_episode=5)
    spawns = [torch.tensor([[8.0, 8.0, 4.0], [5.0, 5.0, 2.0], [12.0, 9.0, 6.0]])]
    one = SdfDagEnv(room, 4, "cpu", base, spawns=spawns)
    two = SdfDagEnv(room, 4, "cpu", replace(base, obs_buffers=2), spawns=spawns)
    assert two.bytes_per_actor() - one.bytes_per_actor() == 3 * 16 * 4 * 4  # one more observation
    a, b = rollout(one, 5, 12), rollout(two, 5, 12)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    two.reset(seed=5)
    g = torch.Generator().manual_seed(1)
    handed = two.step(torch.rand(4, 4, generator=g) * 2 - 1).obs
    kept = handed.clone()
    after = two.step(torch.rand(4, 4, generator=g) * 2 - 1).obs
    assert after.data_ptr() != handed.data_ptr() and torch.equal(handed, kept)
    assert two.previous_obs.data_ptr() == handed.data_ptr()
    with pytest.raises(ValueError, match="obs_buffers=2"):
        _ = one.previous_obs
    with pytest.raises(ValueError, match="obs_buffers"):
        EnvConfig(obs_buffers=3)


def test_truncation_and_scene_rotation_counts() -> None:
    corpus = load_corpus(
        [room_gmdag(), room_gmdag(spawn=(4.0, 4.0, 3.0)), room_gmdag(spawn=(12.0, 12.0, 5.0))], "cpu"
    )
    cfg = EnvConfig(azimuth_bins=16, elevation_bins=4, max_steps_per_episode=5, episodes_per_scene=2)
    spawns = [
        torch.tensor([[8.0, 8.0, 4.0]]),
        torch.tensor([[4.0, 4.0, 3.0]]),
        torch.tensor([[12.0, 12.0, 5.0]]),
    ]
    env = SdfDagEnv(corpus, 4, "cpu", cfg, spawns=spawns)
    env.reset(seed=0)
    assert env.scene.tolist() == [0, 1, 2, 0]
    truncations, rotations = 0, 0
    scene = env.scene.clone()
    for step in range(1, 31):
        out = env.step(torch.zeros(4, 4))
        assert bool(out.truncated.all()) == (step % 5 == 0)
        if step % 5 == 0:
            truncations += 1
            assert torch.all(out.info["episode_length"] == 5)
            assert torch.all(out.obs[:, 2] == 0.0)  # the next episode's first observation
        changed = env.scene != scene
        rotations += int(changed.sum())
        assert bool(changed.any()) == (step % 10 == 0)
        scene = env.scene.clone()
        expected = torch.stack([spawns[s][0] for s in env.scene.tolist()])
        if step % 5 == 0:
            assert torch.allclose(env.position, expected)  # respawned in its (possibly new) scene
    assert truncations == 6 and rotations == 3 * 4
    assert not out.done.any()


def test_starvation_after_void_grace() -> None:
    corpus = load_corpus([open_gmdag()], "cpu")
    cfg = EnvConfig(azimuth_bins=16, elevation_bins=4)
    env = SdfDagEnv(corpus, 2, "cpu", cfg, spawns=[torch.tensor([[2.0, 2.0, 2.0], [14.0, 3.0, 12.0]])])
    env.reset(seed=0)
    ends = []
    for step in range(1, 3 * (cfg.void_grace_steps + 1) + 1):
        out = env.step(torch.zeros(2, 4))
        if out.truncated.any():
            assert bool(out.truncated.all()) and bool(out.info["starved"].all())
            ends.append(step)
    period = cfg.void_grace_steps + 1
    assert ends == [period, 2 * period, 3 * period]


def test_selectable_resolutions(room: SceneCorpus) -> None:
    cfg = EnvConfig(azimuth_bins=384, elevation_bins=72)
    env = SdfDagEnv(room, 1, "cpu", cfg, spawns=[torch.tensor([[8.0, 8.0, 4.0]])])
    obs = env.reset(seed=0)
    assert obs.shape == (1, 3, 384, 72)
    assert float(obs[0, 0].min()) > 0.0 and float(obs[0, 0].max()) < 0.2  # every wall within 20 m


def test_default_spawns_come_from_qualification(room: SceneCorpus) -> None:
    env = SdfDagEnv(room, 2, "cpu", SMALL)
    assert int(env.spawns.count[0]) > 1
    assert float(env.spawns.clearance.min()) >= 0.75
