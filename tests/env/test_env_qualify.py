"""Spawn qualification verdicts on a good scene and on degenerate ones."""

from __future__ import annotations

import numpy as np
import torch

from navi_compiler.dag.build import build_gmdag
from navi_compiler.gmdag import Gmdag
from navi_env.config import EnvConfig, SensorConfig
from navi_env.rays import ray_pattern
from navi_env.space.qualify import (
    QualifyConfig,
    candidate_grid,
    candidate_score,
    observation_profile,
    qualify_scene,
)
from navi_env.tracer.scene import load_corpus
from navi_env.tracer.trace_ref import trace_ref

RES, VOXEL = 32, 0.5


def field(sdf_m: np.ndarray, bounds: tuple[tuple[float, ...], tuple[float, ...]]) -> Gmdag:
    return build_gmdag(
        (sdf_m / VOXEL).astype(np.float32), origin=(0.0, 0.0, 0.0), voxel_size=VOXEL, bounds=bounds
    )


def points() -> np.ndarray:
    i = np.arange(RES + 1, dtype=np.float64) * VOXEL
    return np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)


def room() -> Gmdag:
    q = np.abs(points() - np.array([8.0, 8.0, 4.0])) - np.array([7.0, 7.0, 3.0])
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    return field(-box, ((1.0, 1.0, 1.0), (15.0, 15.0, 7.0)))


def ball_in_the_void() -> Gmdag:
    return field(np.linalg.norm(points() - 8.0, axis=-1) - 1.0, ((0.5, 0.5, 0.5), (15.5, 15.5, 15.5)))


def all_solid() -> Gmdag:
    return field(np.full(points().shape[:3], -5.0), ((0.0, 0.0, 0.0), (16.0, 16.0, 16.0)))


def test_candidate_grid_is_5x7x5_inside_the_bounds() -> None:
    lo, hi = torch.tensor([0.0, -1.0, 2.0]), torch.tensor([5.0, 6.0, 7.0])
    g = candidate_grid(lo, hi, (5, 7, 5))
    assert g.shape == (175, 3)
    assert torch.all((g > lo) & (g < hi))
    assert len(set(g[:, 0].tolist())) == 5 and len(set(g[:, 1].tolist())) == 7


def test_profile_and_score() -> None:
    depth = torch.tensor([[1.0, 100.0, 0.2, 5.0], [3.0, 3.0, 3.0, 3.0]])
    hit = depth < 100.0
    starvation, near = observation_profile(depth, hit, 0.5)
    assert torch.allclose(starvation, torch.tensor([0.25, 0.0])) and torch.allclose(
        near, torch.tensor([0.25, 0.0])
    )
    score = candidate_score(starvation, near, torch.tensor([1.0, 3.0]))
    assert float(score[1]) == 1.0 and float(score[0]) < float(score[1])


def test_a_closed_room_passes() -> None:
    q = qualify_scene(load_corpus([room()], "cpu"), 0)
    assert q.passed and q.verdict == "pass"
    assert q.viable_spawns > 20 and q.best_starvation == 0.0
    spawns = torch.tensor(q.spawns)
    assert torch.all((spawns > torch.tensor([1.5, 1.5, 1.5])) & (spawns < torch.tensor([14.5, 14.5, 6.5])))
    assert q.scores == sorted(q.scores, reverse=True)


def test_the_trace_cost_is_the_envs_mean_steps_per_ray_from_the_best_spawns() -> None:
    """A passing scene's trace cost is the mean number of steps the reference tracer takes per ray of
    the probe pattern from its best spawns, with the env's hit threshold and step cap; a scene that fails
    records none."""
    corpus = load_corpus([room()], "cpu")
    q = qualify_scene(corpus, 0, QualifyConfig(cost_spawns=5))
    spawns = torch.tensor(q.spawns[:5])  # (5, 3)
    dirs = ray_pattern(48, 12, SensorConfig(), torch.device("cpu"))  # (R, 3)
    env = EnvConfig()
    depth = torch.empty(5, dirs.shape[0])  # (5, R)
    steps = torch.empty(5, dirs.shape[0], dtype=torch.int32)  # (5, R)
    trace_ref(corpus, torch.zeros(5, dtype=torch.int64), spawns, dirs, out_depth=depth, out_steps=steps,
              max_steps=env.trace_max_steps, horizon=env.horizon, hit_epsilon=env.hit_epsilon,
              hit_slope=env.hit_slope)  # fmt: skip
    assert q.trace_cost == round(float(steps.double().mean()), 4) and q.trace_cost > 1.0
    assert qualify_scene(load_corpus([all_solid()], "cpu"), 0).trace_cost == 0.0


def test_a_view_of_the_void_fails_on_starvation() -> None:
    q = qualify_scene(load_corpus([ball_in_the_void()], "cpu"), 0)
    assert not q.passed and q.viable_spawns == 0
    assert q.best_starvation >= QualifyConfig().max_starvation
    assert q.free_candidates > 100


def test_an_all_solid_scene_fails_without_free_candidates() -> None:
    q = qualify_scene(load_corpus([all_solid()], "cpu"), 0)
    assert not q.passed and q.free_candidates == 0 and q.viable_spawns == 0 and q.best_starvation == 1.0
    assert set(q.to_json()) >= {"viable_spawns", "best_starvation", "verdict"}
