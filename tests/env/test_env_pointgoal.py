"""Point-goal episodes: the goal mark against its reference and through compact storage, the device table's
path lengths against the per-scene tables, a goal behind a wall marked by direction and distance, the
episode ending at the goal (and not when flying through it), shaping that cannot be farmed, terms within
their bounds, and the scripted baselines beating random."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from navi_compiler.compile import compile_scene
from navi_compiler.ingest.procedural import generate_scene
from navi_env.config import EnvConfig, GoalConfig
from navi_env.sim import goals
from navi_env.sim.env import SdfDagEnv
from navi_env.sim.observation import pack, semantic_table, unpack
from navi_env.sim.rewards import RewardInputs, goal_potential, reward_terms, term_bounds
from navi_env.tracer.scene import load_corpus
from navi_learner.evaluation.baselines import RandomPolicy, goal_seeker_for_env
from navi_learner.evaluation.evaluate import evaluate

from .test_env_env import room_gmdag

SMALL = EnvConfig(task="pointgoal", azimuth_bins=32, elevation_bins=8, max_steps_per_episode=300,
                  goal=GoalConfig(near=2.0, far=30.0))  # fmt: skip


def room_env(actors: int = 8, config: EnvConfig = SMALL, seed: int = 0) -> SdfDagEnv:
    corpus = load_corpus([room_gmdag()], "cpu")
    return SdfDagEnv(corpus, actors, "cpu", config, spawns=[torch.tensor([[8.0, 8.0, 4.0]])], seed=seed)


def test_goal_mark_matches_its_reference() -> None:
    g = torch.Generator().manual_seed(0)
    n = 24
    offset = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([40.0, 40.0, 10.0])  # (N, 3)
    offset[:4] *= 0.01  # bands near the goal
    yaw = (torch.rand(n, generator=g) * 2 - 1) * math.pi  # (N,)
    for cfg in (SMALL, replace(SMALL, azimuth_bins=256, elevation_bins=48)):
        fast = torch.zeros(n, 3, cfg.azimuth_bins, cfg.elevation_bins)
        slow = fast.clone()
        goals.paint_goal(fast, offset, yaw, cfg, torch.tensor(goals.MARK_EDGES))
        goals.paint_goal_ref(slow, offset, yaw, cfg)
        assert torch.equal(fast, slow)
        assert bool((fast[:, 1] < 0).flatten(1).any(dim=1).all())  # every actor sees its goal


def test_goal_marks_survive_compact_storage() -> None:
    g = torch.Generator().manual_seed(1)
    n, az, el = 5, 32, 8
    obs = torch.zeros(n, 3, az, el)
    codes = torch.randint(0, 239, (n, az, el), generator=g, dtype=torch.uint8)  # (N, Az, El) scene classes
    obs[:, 0] = torch.rand(n, az, el, generator=g).half().float()
    obs[:, 1] = semantic_table("cpu")[codes.long()]
    offset = torch.randn(n, 3, generator=g) * 10
    goals.paint_goal(obs, offset, torch.zeros(n), SMALL, torch.tensor(goals.MARK_EDGES))
    depth16 = torch.zeros(2, n, az, el, dtype=torch.float16)
    semantic = torch.zeros(1, n, az, el, dtype=torch.uint8)
    pack(obs, depth16[1], semantic[0])
    back = unpack(
        depth16, semantic, torch.ones(1, n, dtype=torch.bool), semantic_table("cpu", goal_marks=True)
    )
    assert torch.equal(back[0, :, :2], obs[:, :2])


def test_bank_reads_the_tables_path_lengths() -> None:
    env = room_env()
    corpus = env.corpus
    tables = goals.build_tables(corpus, [torch.tensor([[8.0, 8.0, 4.0]])], SMALL.goal, SMALL.drone_radius)
    bank = env.goal_bank
    assert bank is not None
    g = torch.Generator().manual_seed(2)
    points = torch.rand(64, 3, generator=g) * torch.tensor([12.0, 12.0, 4.0]) + torch.tensor([2.0, 2.0, 2.0])
    goal = torch.randint(0, tables[0].goals.shape[0], (64,), generator=g)
    want = tables[0].distance(goal, points)  # (64,)
    got = goals.goal_distance(bank, goal, torch.zeros(64, dtype=torch.long), points)
    assert torch.allclose(got, want, rtol=0, atol=1e-5)
    # every episode starts at a goal the spawn pairs with, within [near, far] along free space
    env.reset(seed=3)
    assert bool(bank.pairs[0, 0, env.goal].all())
    assert bool(
        (env.start_distance >= SMALL.goal.near - 1.0).all()
        and (env.start_distance <= SMALL.goal.far + 1.0).all()
    )


def test_goal_behind_a_wall_is_marked_by_direction_and_distance() -> None:
    scene = compile_scene(generate_scene("rooms", 3), resolution=64)[0]
    corpus = load_corpus([scene], "cpu")
    cfg = replace(SMALL, goal=GoalConfig(near=3.0, far=30.0, per_scene=16))
    env = SdfDagEnv(corpus, 32, "cpu", cfg, seed=0)
    obs = env.reset(seed=0)
    offset = env.goal_position - env.position  # (N, 3)
    ref = torch.zeros_like(obs)
    goals.paint_goal_ref(ref, offset, env.yaw, cfg)
    marked = ref[:, 1] < 0  # (N, Az, El)
    assert torch.equal(obs[:, 1] < 0, marked)
    assert torch.equal(obs[:, 1][marked], ref[:, 1][marked])
    # occluded goals: the depth at the mark's bins is shorter than the goal's distance, still marked
    depth = torch.where(marked, obs[:, 0] * cfg.horizon, torch.inf).flatten(1).amin(dim=1)  # (N,)
    occluded = depth < offset.norm(dim=1) - 1.0  # (N,) a surface well before the goal
    assert int(occluded.sum()) >= 1
    assert bool((env.goal_distance[occluded] > offset.norm(dim=1)[occluded]).all())  # the path goes round


def test_episode_ends_at_the_goal_only_when_slow() -> None:
    env = room_env(2)
    env.reset(seed=0)
    env.position.copy_(env.goal_position)
    env.goal_distance.zero_()
    out = env.step(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))  # 0 flies through, 1 hovers
    assert out.done.tolist() == [False, True] and not bool(out.truncated.any())
    assert out.info["success"].tolist() == [False, True]
    assert float(out.reward_terms["success"][1]) == SMALL.reward.success_weight
    assert int(out.info["episode_length"][1]) == 1 and int(env.steps[1]) == 0  # the next episode began
    assert float(env.path_length[1]) == 0.0 and float(env.start_distance[1]) >= SMALL.goal.near - 1.0


def test_progress_shaping_cannot_be_farmed() -> None:
    """Any closed loop of states earns no net progress shaping (Phi_goal >= 0), however it is flown."""
    cfg = SMALL
    g = torch.Generator().manual_seed(4)
    for _ in range(20):
        loop = torch.rand(16, generator=g) * cfg.goal.far  # progress along a loop of states, meters
        loop = torch.cat([loop, loop[:1]])  # back where it started
        n = loop.shape[0] - 1
        zeros = torch.zeros(n)
        x = RewardInputs(
            contact=torch.zeros(n, dtype=torch.bool), speed=zeros, novel=torch.zeros(n, dtype=torch.bool),
            clearance_before=zeros + 5, clearance=zeros + 5, mid_before=zeros, mid=zeros,
            front_mid_before=zeros, front_mid=zeros, void=zeros, near=zeros,
            progress_before=loop[:-1], progress=loop[1:], success=torch.zeros(n, dtype=torch.bool),
        )  # fmt: skip
        assert float(reward_terms(x, cfg)["progress"].sum()) <= 1e-5
        assert float(goal_potential(loop, cfg.reward).min()) >= 0.0


def test_terms_stay_within_their_bounds_on_random_flights() -> None:
    env = room_env(8)
    env.reset(seed=5)
    bounds = term_bounds(SMALL, SMALL.max_speed * SMALL.dt + 0.1)
    g = torch.Generator().manual_seed(5)
    for _ in range(150):
        out = env.step(torch.rand(8, 4, generator=g) * 2 - 1)
        for name, (lo, hi) in bounds.items():
            term = out.reward_terms[name]
            assert bool((term >= lo - 1e-5).all() and (term <= hi + 1e-5).all()), name


@pytest.mark.parametrize("name", ["greedy", "oracle"])
def test_scripted_goal_seekers_beat_random(name: str) -> None:
    random = evaluate(room_env(8), RandomPolicy(0), 300, seed=0)
    env = room_env(8)
    seeker = evaluate(env, goal_seeker_for_env(name, env), 300, seed=0)
    assert random.task == seeker.task == "pointgoal"
    assert seeker.success_rate >= 0.8 > random.success_rate
    assert seeker.spl >= 0.6 and seeker.collisions_per_episode <= 1.0


@pytest.mark.gpu
def test_cuda_point_goal_step_matches_the_eager_twin() -> None:
    """On CUDA the compiled, graph-replayed point-goal step gives the eager twin's values bit for bit."""
    scene = compile_scene(generate_scene("rooms", 3), resolution=64)[0]
    corpus = load_corpus([scene], "cuda")
    cfg = replace(SMALL, azimuth_bins=64, elevation_bins=16, max_steps_per_episode=40,
                  goal=GoalConfig(near=3.0, far=30.0))  # fmt: skip
    g = torch.Generator(device="cuda").manual_seed(0)
    actions = [torch.rand(64, 4, device="cuda", generator=g) * 2 - 1 for _ in range(60)]
    runs = []
    for eager in (False, True):
        env = SdfDagEnv(corpus, 64, "cuda", cfg, seed=0, eager=eager)
        env.reset(seed=0)
        steps = []
        for a in actions:
            out = env.step(a)
            steps.append(
                [out.obs.clone(), out.reward.clone(), out.done.clone(), out.info["goal_distance"].clone()]
            )
        runs.append(steps)
    for fast_step, eager_step in zip(*runs, strict=True):
        for x, y in zip(fast_step, eager_step, strict=True):
            assert torch.equal(x, y)
