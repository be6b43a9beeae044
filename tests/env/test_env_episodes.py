"""Episode rules as tensor ops: truncation, void grace, scene rotation, spawn tables, random numbers."""

from __future__ import annotations

import torch

from navi_env.config import EnvConfig
from navi_env.sim import rng
from navi_env.sim.episodes import draw_spawns, next_scene, pick_index, rotation, spawn_table, truncation

CFG = EnvConfig()


def test_hard_truncation_at_the_step_limit() -> None:
    steps = torch.tensor([1, 1999, 2000, 2001])
    time_limit, starved = truncation(steps, torch.zeros(4), CFG)
    assert time_limit.tolist() == [False, False, True, True]
    assert not starved.any()


def test_starvation_waits_for_the_void_grace() -> None:
    steps = torch.arange(1, 16)  # steps 1..15 of an episode with a fully void view
    _, starved = truncation(steps, torch.ones(15), CFG)
    assert starved.tolist() == [s > CFG.void_grace_steps for s in range(1, 16)]
    assert int(starved.sum()) == 15 - CFG.void_grace_steps
    _, fine = truncation(steps, torch.full((15,), CFG.starvation_threshold - 0.01), CFG)
    assert not fine.any()


def test_scene_rotation_every_episodes_per_scene() -> None:
    count = torch.zeros(3, dtype=torch.int64)
    rotations = torch.zeros(3, dtype=torch.int64)
    ended = torch.tensor([True, False, True])
    for _ in range(48):
        count, rotate = rotation(count, ended, CFG)
        rotations += rotate
    assert rotations.tolist() == [48 // CFG.episodes_per_scene, 0, 48 // CFG.episodes_per_scene]


def test_next_scene_always_changes_and_covers_the_others() -> None:
    scene = torch.full((4000,), 2, dtype=torch.int64)
    new = next_scene(scene, 5, torch.tensor(7), torch.tensor(3), torch.arange(4000))
    assert not bool((new == 2).any())
    assert set(new.tolist()) == {0, 1, 3, 4}
    assert torch.equal(next_scene(scene, 1, torch.tensor(7), torch.tensor(3), torch.arange(4000)), scene)


def test_spawn_table_pads_and_draws_only_valid_rows() -> None:
    a = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    b = torch.tensor([[9.0, 9, 9]])
    table = spawn_table([a, b], [torch.tensor([1.0, 2.0, 3.0]), torch.tensor([4.0])], "cpu")
    assert table.position.shape == (2, 3, 3) and table.count.tolist() == [3, 1]
    scene = torch.tensor([0] * 500 + [1] * 500)
    pos, clr, yaw, row = draw_spawns(table, scene, torch.tensor(1), torch.tensor(0), torch.arange(1000))
    assert torch.all(pos[500:] == 9.0) and torch.all(clr[500:] == 4.0) and torch.all(row[500:] == 0)
    assert torch.equal(table.position[scene, row], pos)  # the row is the one drawn
    assert set(pos[:500, 0].tolist()) == {0.0, 1.0, 2.0}
    assert torch.equal(clr[:500], pos[:500, 0] + 1.0)  # clearance follows its row
    assert float(yaw.min()) >= -torch.pi and float(yaw.max()) < torch.pi


def test_pick_index_is_in_range() -> None:
    u = torch.tensor([0.0, 0.5, 0.999999, 0.9999999])
    assert pick_index(u, torch.tensor([3, 3, 3, 1])).tolist() == [0, 1, 2, 0]


def test_counter_rng_is_uniform_deterministic_and_keyed() -> None:
    idx = torch.arange(100_000)
    u = rng.uniform(torch.tensor(5), rng.STREAM_SPAWN, torch.tensor(11), idx)
    assert torch.equal(u, rng.uniform(torch.tensor(5), rng.STREAM_SPAWN, torch.tensor(11), idx))
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    assert abs(float(u.mean()) - 0.5) < 0.01
    hist = torch.histc(u, bins=10, min=0.0, max=1.0)
    assert float(hist.min()) > 9_000
    for other in (
        rng.uniform(torch.tensor(6), rng.STREAM_SPAWN, torch.tensor(11), idx),
        rng.uniform(torch.tensor(5), rng.STREAM_YAW, torch.tensor(11), idx),
        rng.uniform(torch.tensor(5), rng.STREAM_SPAWN, torch.tensor(12), idx),
    ):
        assert float((u == other).float().mean()) < 0.01
    z = rng.normal(torch.tensor(5), rng.STREAM_NOISE, torch.tensor(1), idx)
    assert abs(float(z.mean())) < 0.02 and abs(float(z.std()) - 1.0) < 0.02
