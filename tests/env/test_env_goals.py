"""Point-goal tables: the pairing of spawns and goals against Dijkstra, path lengths read between voxel
centres, a goal behind a wall reached the long way round, seeded draws, the room scene (no edge cut,
the same table as the lattice without the edge test), and goals kept on the spawns' side of a closed wall
thinner than the cell."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from navi_env.space.freespace import FreeSpace, free_space, geodesic_ref
from navi_env.space.goal_tables import goal_table, goal_table_ref
from navi_env.tracer.scene import load_corpus

from .test_env_env import room_gmdag
from .test_env_freespace import WALL_CELL, thin_wall_gmdag

CELL = 0.5


def walled(shape: tuple[int, int, int] = (24, 16, 3)) -> FreeSpace:
    """A slab of free voxels cut by a wall across x = 12 with a doorway at the far y end."""
    free = torch.ones(shape, dtype=torch.bool)
    free[12, :-2, :] = False
    return FreeSpace((0.0, 0.0, 0.0), CELL, 0.3, free, torch.where(free, 1.0, 0.0))


SPAWNS = torch.tensor([[1.0, 1.0, 0.6], [5.0, 2.0, 0.6], [10.0, 1.0, 0.6]])  # world meters, left of the wall


def test_pairs_match_dijkstra_and_respect_the_range() -> None:
    space = walled()
    table = goal_table(space, SPAWNS, count=6, near=3.0, far=9.0, goal_clearance=0.5, seed=1)
    assert table.goals.shape == (6, 3) and table.fields.shape == (6, *space.free.shape)
    assert torch.equal(table.pairs, goal_table_ref(table, SPAWNS, 3.0, 9.0))
    assert bool(table.pairs.any(dim=0).all())  # every goal has a spawn
    start = space.voxel(SPAWNS)  # (K, 3)
    for g in range(6):
        ref = geodesic_ref(space.free, table.goals[g][None], CELL)
        reach = ref[start[:, 0], start[:, 1], start[:, 2]]  # (K,)
        assert torch.equal(table.pairs[:, g], (reach >= 3.0) & (reach <= 9.0))
    again = goal_table(space, SPAWNS, count=6, near=3.0, far=9.0, goal_clearance=0.5, seed=1)
    assert torch.equal(again.goals, table.goals) and table.nbytes() > table.fields.numel() * 4


def test_distance_reads_the_field_at_centres_and_goes_round_the_wall() -> None:
    space = walled()
    table = goal_table(space, SPAWNS, count=8, near=3.0, far=40.0, goal_clearance=0.5, seed=2)
    centres = space.centre_of(space.free.nonzero()[:50])  # (50, 3)
    goal = torch.zeros(50, dtype=torch.long)
    want = table.fields[0][tuple(space.voxel(centres).T)]  # (50,)
    assert torch.allclose(table.distance(goal, centres), want)
    between = centres + torch.tensor([0.2, 0.1, 0.05])  # off the centres: never shorter than a hop allows
    got = table.distance(goal, between)
    assert bool((got <= want + (torch.tensor([0.2, 0.1, 0.05]).norm() + 1e-5)).all())
    # a goal right behind the wall, a spawn right in front of it: the path goes via the doorway
    wall_goal = goal_table(space, torch.tensor([[7.0, 1.0, 0.75]]), count=1, near=0.0, far=100.0, seed=0)
    across = wall_goal.distance(torch.zeros(1, dtype=torch.long), torch.tensor([[5.5, 1.0, 0.75]]))
    assert float(across) > 2 * 6.0  # up to the doorway near y = 7 and back, not the 1.5 m through the wall


def test_no_goal_in_range_is_an_error() -> None:
    with pytest.raises(ValueError, match="no goal within"):
        goal_table(walled(), SPAWNS, count=4, near=200.0, far=300.0)
    with pytest.raises(ValueError, match="near < far"):
        goal_table(walled(), SPAWNS, near=5.0, far=5.0)


def test_goals_of_the_room_scene() -> None:
    corpus = load_corpus([room_gmdag()], "cpu")
    space = free_space(corpus, 0)
    spawns = torch.tensor([[8.0, 8.0, 4.0], [3.0, 3.0, 2.0]])
    table = goal_table(space, spawns, count=8, seed=0)  # the default 5-30 m
    assert table.goals.shape[0] == 8 and bool(space.free[tuple(table.goals.T)].all())
    assert bool((space.clearance[tuple(table.goals.T)] >= 0.5).all())
    d = table.distance(torch.arange(8), spawns[torch.zeros(8, dtype=torch.long)])  # (8,) from spawn 0
    straight = (table.positions - spawns[0]).norm(dim=1)  # (8,)
    assert bool((d >= straight - 1e-4).all()) and bool((d <= straight * 1.1 + 0.5).all())  # open room


def test_the_room_s_table_is_the_one_without_the_edge_test() -> None:
    """Nothing stands between the room's free voxel centres: its table (goals, fields, pairs) is the one
    of the same lattice with every edge between free neighbours passable."""
    corpus = load_corpus([room_gmdag()], "cpu")
    space = free_space(corpus, 0)
    spawns = torch.tensor([[8.0, 8.0, 4.0], [3.0, 3.0, 2.0]])
    table = goal_table(space, spawns, count=8, seed=3)
    plain = goal_table(replace(space, edges=None), spawns, count=8, seed=3)
    assert torch.equal(table.goals, plain.goals) and torch.equal(table.pairs, plain.pairs)
    assert torch.equal(table.fields, plain.fields)


def test_goals_stay_on_the_spawns_side_of_a_closed_thin_wall() -> None:
    """A 0.1 m wall across a room at 1.5 m cells: through the edges every goal lies on the spawns' side
    and pairs as Dijkstra says, where the lattice without the edge test draws goals across the wall."""
    wall_x = 8.6
    corpus = load_corpus([thin_wall_gmdag(wall_x, None)], "cpu")
    space = free_space(corpus, 0, WALL_CELL, 0.3)
    spawns = torch.tensor([[3.25, 3.25, 1.75], [6.25, 9.25, 3.25]])  # world meters, left of the wall
    table = goal_table(space, spawns, count=8, near=1.0, far=30.0, seed=0)
    assert bool((table.positions[:, 0] < wall_x).all())
    assert torch.equal(table.pairs, goal_table_ref(table, spawns, 1.0, 30.0))
    across = space.free.nonzero()  # (F, 3) the free voxels ...
    across = across[space.centre_of(across)[:, 0] > wall_x]  # (F', 3) ... right of the wall
    assert bool(torch.isinf(table.fields[:, across[:, 0], across[:, 1], across[:, 2]]).all())
    plain = goal_table(replace(space, edges=None), spawns, count=8, near=1.0, far=30.0, seed=0)
    assert bool((plain.positions[:, 0] > wall_x).any())
