"""The collision table: each contact classed by the surface touched (the field's normal) and the
solid behind it, pinned from the PINNED_STEPS-th contact step in a row (a new episode starts afresh),
pushing where a pinned drone's command points at the nearest surface its view shows, and unseen where the
view's shortest ray is longer than the field's clearance by more than UNSEEN_M."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_compiler.dag.build import build_gmdag
from navi_env.config import EnvConfig
from navi_env.corpus.folder import build_default_corpus
from navi_env.rays import ray_pattern
from navi_env.tracer.analytic_scenes import AnalyticScene, Box, Room
from navi_env.tracer.scene import load_corpus
from navi_learner.evaluation.collisions import COUNTS, PINNED_STEPS, SURFACES, CollisionSites

runner = CliRunner()


def test_collisions_are_classed_by_the_surface_touched_and_what_lies_behind_it() -> None:
    """A room with a 0.2 m plate across it: contacts above the floor, below the ceiling, beside the 1 m
    thick room wall and beside the plate are floor, ceiling, wall and wall + thin."""
    room = Room((1.0, 1.0, 1.0), (5.4, 5.4, 4.0))
    plate = Box((3.1, 1.0, 1.0), (3.3, 4.0, 4.0))
    scene = AnalyticScene((room, plate), resolution=64, voxel_size=0.1)
    gmdag = build_gmdag(scene.lattice(), origin=(0.0, 0.0, 0.0), voxel_size=0.1, bounds=(room.lo, room.hi))
    env = SimpleNamespace(corpus=load_corpus([gmdag], "cpu"))
    points = torch.tensor(
        [[2.0, 2.0, 1.2], [2.0, 2.0, 3.8], [1.2, 2.0, 2.5], [2.9, 2.0, 2.5], [2.0, 5.0, 2.5]]
    )  # (5, 3) floor, ceiling, room wall, plate, room wall
    hit = torch.tensor([True, True, True, True, False])  # (5,) the last is no contact
    sites = CollisionSites()
    sites(step(hit, points))
    rows = sites.classify(env, ("room",))
    assert (
        rows["room"]
        == rows["all"]
        == {
            "floor": 1,
            "ceiling": 1,
            "wall": 2,
            "slope": 0,
            "thin": 1,
            "pinned": 0,
            "pushing": 0,
            "unseen": 0,
        }
    )
    assert set(rows["all"]) == {*SURFACES, "thin", "pinned", "pushing", "unseen"}
    assert CollisionSites().classify(env, ("room",))["all"] == dict.fromkeys(
        (*SURFACES, "thin", "pinned", "pushing", "unseen"), 0
    )


def step(hit: torch.Tensor, points: torch.Tensor, ends: torch.Tensor | None = None) -> SimpleNamespace:
    """A step's output as CollisionSites reads it: contact, scene 0, position, episode ends."""
    n = hit.shape[0]
    done = torch.zeros(n, dtype=torch.bool) if ends is None else ends  # (N,)
    info = {"collision": hit, "scene_id": torch.zeros(n, dtype=torch.long), "position": points}
    return SimpleNamespace(info=info, done=done, truncated=torch.zeros(n, dtype=torch.bool))


def test_a_contact_is_pinned_from_the_tenth_step_in_a_row_and_a_new_episode_starts_afresh() -> None:
    """Three drones against the room's floor: one pressed for 14 steps (5 pinned contacts), one that
    touches every other step (never pinned), one pressed for 9 steps, then a new episode, then 9 more
    (18 contacts, none pinned: the run restarts with the episode)."""
    room = Room((1.0, 1.0, 1.0), (5.4, 5.4, 4.0))
    scene = AnalyticScene((room,), resolution=64, voxel_size=0.1)
    gmdag = build_gmdag(scene.lattice(), origin=(0.0, 0.0, 0.0), voxel_size=0.1, bounds=(room.lo, room.hi))
    env = SimpleNamespace(corpus=load_corpus([gmdag], "cpu"))
    points = torch.tensor([[2.0, 2.0, 1.2], [3.0, 2.0, 1.2], [4.0, 2.0, 1.2]])  # (3, 3) on the floor
    sites = CollisionSites()
    for t in range(18):
        hit = torch.tensor([t < 14, t % 2 == 0, True])  # (3,)
        sites(step(hit, points, ends=torch.tensor([False, False, t == 8])))
    rows = sites.classify(env, ("room",))
    assert rows["all"]["floor"] == 14 + 9 + 18
    assert rows["all"]["pinned"] == 14 - (PINNED_STEPS - 1) == 5


def test_a_pinned_drone_pushing_into_the_floor_it_sees_and_a_contact_no_ray_showed() -> None:
    """Three drones 0.32 m over the room's floor, in contact for 12 steps (3 pinned contacts each): the
    first sees the floor straight below and commands full descent (pushing), the second sees it too but
    commands a climb (pinned, not pushing), the third commands descent while every ray of its view reads
    the horizon (12 unseen contacts; a view with no hit shows nothing to push into)."""
    room = Room((1.0, 1.0, 1.0), (5.4, 5.4, 4.0))
    scene = AnalyticScene((room,), resolution=64, voxel_size=0.1)
    gmdag = build_gmdag(scene.lattice(), origin=(0.0, 0.0, 0.0), voxel_size=0.1, bounds=(room.lo, room.hi))
    env = SimpleNamespace(corpus=load_corpus([gmdag], "cpu"))
    config = EnvConfig()
    az, el = 8, 6
    rays = ray_pattern(az, el, config.sensor)  # (R, 3) body frame
    down = int(rays[:, 2].argmin())  # the ray nearest straight down
    obs = torch.ones(3, 3, az, el)  # (N, C, Az, El) every ray a miss
    obs[:2, 0].view(2, az * el)[:, down] = 0.32 / config.horizon  # the floor below drones 0 and 1
    action = torch.tensor([[0.0, -1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0]])  # (3, 4)
    points = torch.tensor([[2.0, 2.0, 1.32], [3.0, 2.0, 1.32], [4.0, 2.0, 1.32]])  # (3, 3)
    sites = CollisionSites(config)
    for _ in range(12):
        out = step(torch.ones(3, dtype=torch.bool), points)
        out.obs = obs
        out.info["clearance"] = torch.full((3,), 0.32)
        sites(out, action)
    rows = sites.classify(env, ("room",))
    assert rows["all"]["floor"] == 36
    assert rows["all"]["pinned"] == 3 * (12 - (PINNED_STEPS - 1)) == 9
    assert rows["all"]["unseen"] == 12
    assert rows["all"]["pushing"] == 3  # drone 0 only: drone 1 climbs away, drone 2's view shows nothing


def test_navi_evaluate_counts_every_collision_once_per_scene(tmp_path: Path) -> None:
    """`navi evaluate --collisions` on a small maze: every contact the metrics count is classed by exactly
    one surface, per scene and in all; pinned, pushing and unseen are parts of it, and the markdown
    table names the scene. The toy env (no distance field) is refused."""
    corpus = tmp_path / "maze"
    build_default_corpus(corpus, 32, 1, 3, families=["maze"])
    args = ["evaluate", "--policy", "random", "--corpus", str(corpus), "--actors", "6", "--steps", "150"]
    out = runner.invoke(build_app(), [*args, "--device", "cpu", "--collisions", "--json"])
    assert out.exit_code == 0, out.stdout + out.stderr
    result = json.loads(out.stdout)
    metrics, table = result["results"][0], result["collisions"]
    contacts = round(metrics["collisions_per_1k"] * 6 * 150 / 1000)
    assert contacts > 0 and set(table["all"]) == set(COUNTS)
    assert sum(table["all"][s] for s in SURFACES) == contacts
    (scene,) = [k for k in table if k != "all"]
    assert table[scene] == table["all"] and scene.startswith("maze")
    assert (
        table["all"]["pushing"] <= table["all"]["pinned"] <= contacts and table["all"]["unseen"] <= contacts
    )
    text = runner.invoke(build_app(), [*args, "--device", "cpu", "--collisions"]).stdout
    assert f"| {scene} | " in text and "| pushing | unseen |" in text
    toy = runner.invoke(build_app(), ["evaluate", "--policy", "random", "--env", "toy", "--collisions"])
    assert toy.exit_code != 0 and "needs the drone env" in toy.stdout + toy.stderr
