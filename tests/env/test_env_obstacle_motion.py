"""Scripted moving obstacles in the drone env (navi_env.sim.obstacles, EnvConfig.obstacles).

The vectorised primitive distance matches its float64 twin; the sweep stops fast and thin obstacles
at the drone and never lets them through (checked along every swept path); obstacles stay out of the
static geometry and on their scripts; physics, the view and the rewards all see the combined field;
collisions with obstacles are counted; placement and re-placement at episode ends keep their rules.
"""

from __future__ import annotations

import json
import math
import typing
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from navi.cli import build_app
from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import Gmdag, write_gmdag
from navi_env.config import EnvConfig, ObstacleConfig
from navi_env.sim import obstacles as om
from navi_env.sim.env import SdfDagEnv
from navi_env.tracer import primitives as ob
from navi_env.tracer.scene import SceneCorpus, load_corpus
from navi_env.tracer.trace import sample_distance

RES, VOXEL = 32, 0.625  # a 20 m cube
LO, HI = (1.0, 1.0, 1.0), (19.0, 19.0, 9.0)


def _room_gmdag() -> Gmdag:
    i = np.arange(RES + 1, dtype=np.float64) * VOXEL
    p = np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)  # (R+1, R+1, R+1, 3)
    c, h = (np.array(LO) + np.array(HI)) / 2, (np.array(HI) - np.array(LO)) / 2
    q = np.abs(p - c) - h
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    pillar = np.linalg.norm(p[..., :2] - np.array([12.0, 7.0]), axis=-1) - 1.0  # floor-to-ceiling column
    d = np.minimum(-box, pillar)
    spawns = torch.cat(_spawns()).numpy()
    return build_gmdag(
        (d / VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=VOXEL,
        bounds=(LO, HI),
        spawns=spawns,
    )


def _room() -> SceneCorpus:
    return load_corpus([_room_gmdag()], "cpu")


@pytest.fixture(scope="module")
def room() -> SceneCorpus:
    return _room()


def _spawns() -> list[torch.Tensor]:
    xs = torch.arange(3.0, 18.0, 2.5)
    grid = torch.stack(torch.meshgrid(xs, xs, torch.tensor([3.0, 5.5]), indexing="ij"), dim=-1).reshape(-1, 3)
    keep = (grid[:, :2] - torch.tensor([12.0, 7.0])).norm(dim=1) > 2.5  # off the pillar
    return [grid[keep]]


def _env(room: SceneCorpus, n: int, obstacles: ObstacleConfig, **kw: typing.Any) -> SdfDagEnv:
    cfg = EnvConfig(azimuth_bins=64, elevation_bins=16, obstacles=obstacles, **kw)
    return SdfDagEnv(room, n, "cpu", cfg, spawns=_spawns(), seed=3)


def _random_records(count: int, seed: int) -> torch.Tensor:
    """(count, 16) records of every kind around the origin."""
    g = np.random.default_rng(seed)
    out = []
    for i in range(count):
        c = g.uniform(-1.0, 1.0, 3).tolist()
        kind = 1 + i % 4
        if kind == ob.SPHERE:
            out.append(ob.record(ob.SPHERE, c, radius=float(g.uniform(0.1, 1.0))))
        elif kind == ob.CAPSULE:
            out.append(ob.record(ob.CAPSULE, c, radius=0.3, axis=g.normal(0, 0.7, 3).tolist()))
        elif kind == ob.BOX:
            out.append(ob.record(ob.BOX, c, axis=g.uniform(0.02, 1.0, 3).tolist()))
        else:
            out.append(
                ob.record(ob.OBB, c, axis=g.uniform(0.02, 1.0, 3).tolist(), quat=g.normal(size=4).tolist())
            )
    return torch.stack(out)


def test_vectorised_distance_matches_the_twin_and_the_bound_holds() -> None:
    recs = _random_records(40, 0)  # (40, 16)
    g = torch.Generator().manual_seed(1)
    points = torch.rand(40, 50, 3, generator=g) * 6.0 - 3.0  # (40, 50, 3)
    fast = ob.distance(recs[:, None, :], points)  # (40, 50)
    for i in range(40):
        ref = [ob.distance_one(recs[i].tolist(), p) for p in points[i].tolist()]
        assert np.allclose(fast[i].numpy(), ref, atol=2e-5), i
    empty = torch.zeros(ob.WORDS)
    assert math.isinf(float(ob.distance(empty, torch.zeros(3))))
    # The bounding sphere holds the primitive: points on it are never inside.
    dirs = torch.randn(40, 200, 3, generator=g)
    dirs = dirs / dirs.norm(dim=2, keepdim=True)
    centers = recs[:, ob.CENTER : ob.CENTER + 3]  # (40, 3)
    on_sphere = centers[:, None, :] + ob.bounding_radius(recs)[:, None, None] * dirs  # (40, 200, 3)
    assert float(ob.distance(recs[:, None, :], on_sphere).min()) >= -1e-5


@pytest.mark.parametrize("kind", ["sphere", "thin_box", "capsule", "obb"])
@pytest.mark.parametrize("speed", [4.0, 60.0])
def test_sweep_stops_fast_and_thin_obstacles_at_the_drone(kind: str, speed: float) -> None:
    """An obstacle 3 m away moving straight at the drone by `speed` x 0.1 s (up to 6 m: through the drone
    and beyond) stops touching the drone sphere, and no point of its swept path comes closer."""
    radius = 0.3
    start = [3.0, 0.05, -0.02]
    recs = {
        "sphere": ob.record(ob.SPHERE, start, radius=0.2),
        "thin_box": ob.record(ob.BOX, start, axis=(0.005, 1.0, 1.0)),  # a 1 cm plate moving along x
        "capsule": ob.record(ob.CAPSULE, start, radius=0.05, axis=(0.0, 0.0, 0.6)),
        "obb": ob.record(ob.OBB, start, axis=(0.01, 0.5, 0.3), quat=(0.9, 0.1, 0.3, 0.0)),
    }
    rec = recs[kind][None, None, :]  # (1, 1, 16)
    delta = torch.tensor([[[-speed * 0.1, 0.0, 0.0]]])  # (1, 1, 3)
    drone = torch.zeros(1, 3)
    t, gap = om.sweep(rec, delta, drone, radius, iterations=16)
    if speed * 0.1 < 3.0 - 1.05:  # too slow to reach the drone this step
        assert float(t) == 1.0
        return
    assert float(t) < 1.0
    assert radius + om.SKIN - 1e-5 <= float(gap) <= radius + om.TOUCH
    for s in torch.linspace(0.0, float(t), 200):
        assert float(ob.distance(rec, drone[:, None, :] - s * delta)) >= radius - 1e-5


def _sweep_case(n: int, k: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n actors x k primitives of every kind (one slot in five empty) 0.5-3 m from each actor's drone,
    moving 0-6 m this step, a third of them straight at the drone: records, deltas, drones."""
    g = torch.Generator().manual_seed(seed)
    recs = _random_records(n * k, seed).reshape(n, k, ob.WORDS).clone()  # (N, K, 16)
    recs[:, ::5, ob.KIND] = float(ob.NONE)
    drone = torch.rand(n, 3, generator=g) * 4.0 - 2.0  # (N, 3)
    centre = recs[..., ob.CENTER : ob.CENTER + 3] + drone[:, None, :]  # (N, K, 3) around the drone
    away = centre - drone[:, None, :]  # (N, K, 3)
    recs[..., ob.CENTER : ob.CENTER + 3] = drone[:, None, :] + away / away.norm(dim=-1, keepdim=True) * (
        0.5 + 2.5 * torch.rand(n, k, 1, generator=g)
    )
    delta = torch.randn(n, k, 3, generator=g) * 2.0  # (N, K, 3)
    at_drone = drone[:, None, :] - recs[..., ob.CENTER : ob.CENTER + 3]  # (N, K, 3)
    aim = torch.rand(n, k, generator=g) < 0.33  # (N, K)
    delta = torch.where(aim[..., None], at_drone * (1.0 + torch.rand(n, k, 1, generator=g)), delta)
    return recs, delta, drone


def test_the_sweep_launch_matches_its_torch_twin() -> None:
    """sweep (one launch of the tracer library) against sweep_ref (torch ops): the same fractions and
    distances on 4,096 primitives of every kind, empty slots included, a third aimed at the drone."""
    recs, delta, drone = _sweep_case(512, 8, 3)
    t, dist = om.sweep(recs, delta, drone, 0.3, iterations=16)  # (N, K), (N, K)
    t_ref, dist_ref = om.sweep_ref(recs, delta, drone, 0.3, iterations=16)
    empty = recs[..., ob.KIND] == ob.NONE  # (N, K)
    assert bool((t[empty] == 1.0).all()) and bool(torch.isinf(dist[empty]).all())
    assert bool(torch.isinf(dist_ref[empty]).all())
    assert float((t - t_ref).abs().max()) < 1e-4
    full = ~empty
    assert float((dist[full] - dist_ref[full]).abs().max()) < 1e-4
    stopped = (t < 1.0).sum()
    assert 100 < int(stopped) < int(full.sum())  # both outcomes are exercised
    with pytest.raises(ValueError, match="delta"):
        om.sweep(recs, delta[:, :4], drone, 0.3, iterations=16)
    with pytest.raises(ValueError, match="iterations"):
        om.sweep(recs, delta, drone, 0.3, iterations=0)


@pytest.mark.gpu
def test_the_sweep_agrees_on_cpu_and_cuda() -> None:
    recs, delta, drone = _sweep_case(1024, 8, 4)
    t, dist = om.sweep(recs, delta, drone, 0.3, iterations=16)
    t_gpu, dist_gpu = om.sweep(recs.cuda(), delta.cuda(), drone.cuda(), 0.3, iterations=16)
    assert float((t - t_gpu.cpu()).abs().max()) < 1e-4
    full = recs[..., ob.KIND] != ob.NONE
    assert float((dist[full] - dist_gpu.cpu()[full]).abs().max()) < 1e-4


def _swept_ok(before: torch.Tensor, after: torch.Tensor, drone: torch.Tensor, radius: float) -> float:
    """Smallest distance from the drone (N, 3) to each obstacle along its straight move before -> after
    (N, K, 16 records), sampled at 65 fractions."""
    delta = after[..., ob.CENTER : ob.CENTER + 3] - before[..., ob.CENTER : ob.CENTER + 3]  # (N, K, 3)
    worst = math.inf
    for s in torch.linspace(0.0, 1.0, 65):
        d = ob.distance(before, drone[:, None, :] - s * delta)  # (N, K)
        worst = min(worst, float(d.min()))
    return worst - radius


def test_fast_obstacles_never_pass_through_drones_nor_walls(room: SceneCorpus) -> None:
    """Obstacles at 20-60 m/s (2-6 m a step, faster than any drone) among drones flying at random: along
    every obstacle's swept path the drone stays outside it, along every drone move every obstacle stays
    clear of the drone, obstacles keep out of the static geometry and on their scripts, and the collisions
    they cause are counted."""
    cfg = ObstacleConfig(count=6, speed_min=20.0, speed_max=60.0, reach_min=2.0, reach_max=6.0, place_max=8.0)
    env = _env(room, 8, cfg)
    env.reset(seed=5)
    assert env.obstacles is not None
    radius = env.config.drone_radius
    g = torch.Generator().manual_seed(0)
    struck = 0
    for _ in range(60):
        before = env.obstacles.prims.clone()  # (N, K, 16)
        drone_before = env.position.clone()  # (N, 3)
        out = env.step(torch.rand(8, 4, generator=g) * 2 - 1)
        if bool(out.truncated.any()):
            continue  # re-placed: checked by the placement test
        after = env.obstacles.prims
        assert _swept_ok(before, after, drone_before, radius) >= -1e-4
        # the drone's own move, against the obstacles where they stopped
        for s in torch.linspace(0.0, 1.0, 33):
            p = drone_before + s * (env.position - drone_before)  # (N, 3)
            assert float(om.obstacle_distance(env.obstacles, p).min()) >= 0.5 * radius - 1e-4
        assert float(om.obstacle_distance(env.obstacles, env.position).min()) >= radius - 1e-4
        active = after[..., ob.KIND] != ob.NONE  # (N, K)
        centers = after[..., ob.CENTER : ob.CENTER + 3]  # (N, K, 3)
        static = sample_distance(
            room, torch.zeros(8 * cfg.count, dtype=torch.int64), centers.reshape(-1, 3).contiguous()
        )
        worst = (static.reshape(8, -1) - env.obstacles.bound)[active]
        assert bool((worst >= -1e-3).all()), (worst.min(), static.reshape(8, -1)[active][worst.argmin()])
        rel = centers - env.obstacles.anchor  # (N, K, 3)
        motion = env.obstacles.motion[None, :].expand(8, -1)
        along = (rel * env.obstacles.axis).sum(-1)  # (N, K)
        across = (rel - along[..., None] * env.obstacles.axis).norm(dim=-1)  # (N, K)
        lin = active & (motion == om.LINEAR)
        assert bool((along.abs() <= env.obstacles.reach + 1e-4)[lin].all())
        assert bool((across < 1e-3)[lin].all())
        circ = active & (motion == om.CIRCULAR)
        assert bool((rel[..., :2].norm(dim=-1) <= env.obstacles.reach + 1e-4)[circ].all())
        walk = active & (motion == om.RANDOM_WALK)
        assert bool((rel.norm(dim=-1) <= env.obstacles.reach + 1e-4)[walk].all())
        hit = out.info["obstacle_collision"]
        assert bool((out.info["collision"] | ~hit).all())  # an obstacle collision is a collision
        struck += int(hit.sum())
    assert struck > 0, "the fast obstacles never reached a drone: the test exercised nothing"


def _one_obstacle(env: SdfDagEnv, rec: torch.Tensor, axis: tuple[float, float, float], speed: float) -> None:
    """Replace actor 0's single slot by `rec`, moving linearly along `axis` at `speed`."""
    st = env.obstacles
    assert st is not None
    st.prims[0, 0] = rec
    center = rec[ob.CENTER : ob.CENTER + 3]
    st.anchor[0, 0] = center
    st.axis[0, 0] = torch.tensor(axis)
    st.phase[0, 0] = 0.0
    st.speed[0, 0] = speed
    st.reach[0, 0] = 20.0
    st.bound[0, 0] = ob.bounding_radius(rec)
    st.clearance[0, 0] = sample_distance(env.corpus, torch.zeros(1, dtype=torch.int64), center[None])[0]


def test_an_obstacle_thrown_at_a_hovering_drone_is_a_counted_collision(room: SceneCorpus) -> None:
    cfg = ObstacleConfig(count=1, shapes=("sphere",), motions=("linear",))
    env = _env(room, 1, cfg)
    env.reset(seed=0)
    drone = env.position[0].clone()
    inward = torch.tensor([10.0, 10.0, drone[2]]) - drone
    inward = inward / inward.norm()  # toward the middle of the room: free space behind the obstacle
    start = drone + 4.0 * inward
    _one_obstacle(env, ob.record(ob.SPHERE, start.tolist(), radius=0.4), tuple((-inward).tolist()), 50.0)
    out = env.step(torch.zeros(1, 4))  # it comes 5 m this step: it would pass right through the drone
    center = env.obstacles.prims[0, 0, ob.CENTER : ob.CENTER + 3].clone()  # type: ignore[union-attr]
    gap = float((center - drone).norm()) - 0.4 - env.config.drone_radius
    assert -1e-4 <= gap <= om.TOUCH + 1e-4  # stopped at the drone, on the near side
    assert float((center - drone) @ inward) > 0.0
    assert bool(out.info["collision"][0]) and bool(out.info["obstacle_collision"][0])
    assert float(out.reward_terms["collision"][0]) <= -env.config.reward.collision_base + 1e-6
    assert float(out.info["clearance"][0]) < 0.4  # the view's clearance sees it
    # the view: rays that look at it report semantic 1 + obstacle class at its surface
    hits = env.semantic[0] == cfg.semantic_class + 1  # (R,)
    assert bool(hits.any())
    assert float(env.depth[0][hits].min()) == pytest.approx(env.config.drone_radius + gap, abs=0.03)
    out = env.step(torch.zeros(1, 4))  # it turned back: no second collision, it moves away
    assert not bool(out.info["obstacle_collision"][0])
    moved = env.obstacles.prims[0, 0, ob.CENTER : ob.CENTER + 3] - center  # type: ignore[union-attr]
    assert float(moved @ inward) > 1.0


def test_a_drone_flying_into_a_parked_obstacle_stops_at_it(room: SceneCorpus) -> None:
    """Physics sees the combined field: flying at a still box, the drone stops outside it and the contact
    counts as an obstacle collision."""
    cfg = ObstacleConfig(count=1, shapes=("box",), motions=("linear",))
    env = _env(room, 1, cfg, limiter_min_fraction=1.0)
    env.reset(seed=0)
    drone = env.position[0].clone()
    ahead = torch.tensor([math.cos(float(env.yaw[0])), math.sin(float(env.yaw[0])), 0.0])
    box = ob.record(ob.BOX, (drone + 2.0 * ahead).tolist(), axis=(0.3, 0.3, 0.3))
    _one_obstacle(env, box, (1.0, 0.0, 0.0), 0.0)
    radius = env.config.drone_radius
    for _ in range(10):
        out = env.step(torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
        assert float(om.obstacle_distance(env.obstacles, env.position)[0]) >= radius - 1e-4  # type: ignore[arg-type]
        if bool(out.info["obstacle_collision"][0]):
            break
    else:
        raise AssertionError("the drone never reached the box 2 m ahead")
    assert bool(out.info["collision"][0])
    assert float((env.position[0] - drone) @ ahead) <= 2.0 - 0.3 - radius + 1e-3  # held at the near face


def test_placement_and_replacement_at_episode_end(room: SceneCorpus) -> None:
    cfg = ObstacleConfig(count=8)
    env = _env(room, 6, cfg, max_steps_per_episode=4)
    env.reset(seed=2)
    st = env.obstacles
    assert st is not None
    radius = env.config.drone_radius

    def check(mask: torch.Tensor) -> None:
        active = (st.prims[..., ob.KIND] != ob.NONE) & mask[:, None]  # (N, K)
        centers = st.prims[..., ob.CENTER : ob.CENTER + 3]  # (N, K, 3)
        far = (centers - env.position[:, None, :]).norm(dim=-1)  # (N, K)
        near_limit = torch.clamp_min(st.bound + radius + om.PLACE_MARGIN, cfg.place_min)
        assert bool((far >= near_limit - 1e-5)[active].all()) and bool(
            (far <= cfg.place_max + 1e-5)[active].all()
        )
        assert bool((st.clearance >= st.bound)[active].all())
        kinds = st.prims[..., ob.KIND][active]
        assert set(kinds.long().tolist()) <= {ob.SPHERE, ob.CAPSULE, ob.BOX, ob.OBB}

    check(torch.ones(6, dtype=torch.bool))
    assert int((st.prims[..., ob.KIND] != ob.NONE).sum()) >= 24  # most slots find a place in this room
    before = st.prims.clone()
    for _ in range(4):
        out = env.step(torch.zeros(6, 4))
    assert bool(out.truncated.all())
    check(out.truncated)
    assert not torch.equal(before[..., ob.CENTER : ob.CENTER + 3], st.prims[..., ob.CENTER : ob.CENTER + 3])


def test_seeded_obstacle_rollouts_repeat_and_no_obstacles_changes_nothing(room: SceneCorpus) -> None:
    def run(count: int) -> list[torch.Tensor]:
        env = _env(room, 4, ObstacleConfig(count=count))
        frames = [env.reset(seed=7).clone()]
        g = torch.Generator().manual_seed(1)
        for _ in range(8):
            out = env.step(torch.rand(4, 4, generator=g) * 2 - 1)
            frames += [out.obs.clone(), out.reward.clone(), out.info["position"].clone()]
            if env.obstacles is not None:
                frames.append(env.obstacles.prims.clone())
        return frames

    a, b = run(4), run(4)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    plain = run(0)
    env = _env(room, 4, ObstacleConfig())
    assert env.obstacles is None
    assert len(plain) == 1 + 3 * 8


def test_obstacle_config_rejects_bad_values() -> None:
    for bad in (
        {"count": -1},
        {"count": 65},
        {"shapes": ("cube",)},
        {"motions": ()},
        {"size_min": 0.0},
        {"speed_min": 2.0, "speed_max": 1.0},
        {"place_min": 5.0, "place_max": 4.0},
        {"place_tries": 0},
    ):
        with pytest.raises(ValueError):
            ObstacleConfig(**bad)


def test_bench_env_with_moving_obstacles(tmp_path: Path) -> None:
    path = tmp_path / "room.gmdag"
    write_gmdag(_room_gmdag(), path)

    actors, steps = 32, 40

    def run(k: int) -> dict[str, typing.Any]:
        args = f"bench env --gmdag {path} --actors {actors} --steps {steps} --azimuth 32 --elevation 8"
        res = CliRunner().invoke(build_app(), [*args.split(), "--obstacles", str(k), "--json"])
        assert res.exit_code == 0, res.output
        return dict(json.loads(res.stdout.strip().splitlines()[-1]))

    plain, crowded = run(0), run(16)
    assert plain["obstacles_per_actor"] == 0 and "obstacle_hit_fraction" not in plain
    assert crowded["obstacles_per_actor"] == 16 and crowded["obstacle_hit_fraction"] > 0.0
    # the same seeded flight replayed here (5 warm-up steps, a timed pass, the counted pass), counted here
    env = SdfDagEnv(
        _room(), actors, "cpu", EnvConfig(azimuth_bins=32, elevation_bins=8, obstacles=ObstacleConfig(count=16)),
        seed=0,
    )  # fmt: skip
    g = torch.Generator().manual_seed(0)
    env.reset(seed=0)
    struck = 0
    for i in range(5 + 2 * steps):
        out = env.step(torch.empty(actors, 4).uniform_(-1.0, 1.0, generator=g))
        struck += int(out.info["obstacle_collision"].sum()) if i >= 5 + steps else 0
    assert struck > 0, "no drone met an obstacle: the test exercised nothing"
    assert crowded["obstacle_collisions_per_1k"] == pytest.approx(
        1000.0 * struck / (steps * actors), abs=1e-3
    )
    assert crowded["bytes_per_actor"] > plain["bytes_per_actor"]  # the obstacle state is counted


def test_squad_drones_see_and_never_pass_through_each_other(room: SceneCorpus) -> None:
    """Two drones of a squad flying head-on at full speed: each sees the other (semantic 1 + drone class),
    never its own sphere; they stop short of each other (>= 2 radii apart at every step end, never
    crossing on the way) and the bump counts as a drone collision in the collision term."""
    cfg = ObstacleConfig(squad=2)
    env = _env(room, 2, cfg, limiter_min_fraction=1.0)
    env.reset(seed=0)
    radius = env.config.drone_radius
    env.position.copy_(torch.tensor([[8.0, 11.0, 5.0], [12.0, 11.0, 5.0]]))
    env.yaw.copy_(torch.tensor([0.0, math.pi]))
    bumped = False
    for _ in range(12):
        before = env.position.clone()
        out = env.step(torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]))
        after = env.position
        assert float((after[0] - after[1]).norm()) >= 2 * radius - 1e-4
        assert float(after[0, 0]) < float(after[1, 0])  # never passed each other
        for s in torch.linspace(0.0, 1.0, 33):
            a, b = before + s * (after - before)
            assert float((a - b).norm()) >= 1.5 * radius - 1e-4
        if bool(out.info["drone_collision"].any()):
            bumped = True
            assert bool(out.info["collision"][out.info["drone_collision"]].all())
            assert float(out.reward_terms["collision"][out.info["drone_collision"]].max()) < 0.0
    assert bumped
    code = cfg.drone_class + 1
    gap = float((env.position[0] - env.position[1]).norm())
    for me in range(2):
        sees = env.semantic[me] == code  # (R,)
        assert bool(sees.any())  # the other drone, ahead
        assert float(env.depth[me][sees].min()) >= gap - 2 * radius - 0.05  # not its own sphere


def test_squads_share_scenes_and_change_them_together() -> None:
    corpus = load_corpus([_room_gmdag(), _room_gmdag()], "cpu")
    cfg = EnvConfig(
        azimuth_bins=32,
        elevation_bins=8,
        max_steps_per_episode=3,
        episodes_per_scene=2,
        obstacles=ObstacleConfig(squad=2),
    )
    env = SdfDagEnv(corpus, 4, "cpu", cfg, spawns=_spawns() * 2, seed=1)
    env.reset(seed=1)
    assert env.scene.tolist() == [0, 0, 1, 1]
    assert bool((env.position[0] != env.position[1]).any())  # members start apart
    g = torch.Generator().manual_seed(0)
    changes = 0
    for _ in range(30):
        scene = env.scene.clone()
        out = env.step(torch.rand(4, 4, generator=g) * 2 - 1)
        assert env.scene[0] == env.scene[1] and env.scene[2] == env.scene[3]
        moved = env.scene != scene  # (N,)
        assert bool(out.truncated[moved].all())  # nobody changes scene mid-episode
        changes += int(moved.sum())
    assert changes >= 4
    with pytest.raises(ValueError, match="squad"):
        SdfDagEnv(corpus, 3, "cpu", cfg, spawns=_spawns() * 2)


@pytest.mark.gpu
def test_fused_obstacle_passes_match_the_eager_kernels_on_cuda(room: SceneCorpus) -> None:
    """On CUDA the obstacles' placement, script, move and nearest-obstacle distance run as compiled
    passes. The same seeded rollout on the CUDA path and on the eager twin (`eager=True`): the same
    collisions, the obstacles within float32 reassociation of each other, and the same frames."""
    cuda = load_corpus([_room_gmdag()], "cuda")

    def run(fused: bool) -> list[torch.Tensor]:
        cfg = EnvConfig(azimuth_bins=64, elevation_bins=16, obstacles=ObstacleConfig(count=6))
        spawns = [s.cuda() for s in _spawns()]
        env = SdfDagEnv(cuda, 64, "cuda", cfg, spawns=spawns, seed=3, eager=not fused)
        env.reset(seed=7)
        g = torch.Generator(device="cuda").manual_seed(1)
        frames = []
        for _ in range(12):
            out = env.step(torch.rand(64, 4, generator=g, device="cuda") * 2 - 1)
            assert env.obstacles is not None
            frames += [env.obstacles.prims.clone(), out.info["obstacle_collision"].clone(), out.obs.clone()]
        return frames

    eager, fused = run(False), run(True)
    for i, (x, y) in enumerate(zip(eager, fused, strict=True)):
        if x.dtype == torch.bool:
            assert torch.equal(x, y), i
        else:
            assert float((x - y).abs().max()) < 1e-3, i
