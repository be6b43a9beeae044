"""The batched env as the ecosystem adapters see it: built from a corpus folder with two observation
buffers written in turn (consecutive steps hand out distinct tensors, no copy), and its bounds. Torch
only (no RL library)."""

from __future__ import annotations

import os
from dataclasses import replace

import torch

from navi_env.config import POINTGOAL_EPISODE_STEPS, EnvConfig
from navi_env.corpus.folder import load_corpus_folder
from navi_env.sim.env import SdfDagEnv

ACTION_DIM = 4
"""Actions (N, 4) in [-1, 1]: forward, vertical, lateral, yaw rate (body frame, docs/SIMULATION.md)."""
OBS_LOW = (0.0, 0.0, -1.0)
"""Lowest value per channel: depth / horizon, semantic, delta depth (exploration)."""
OBS_LOW_POINTGOAL = (0.0, -1.0, -1.0)
"""Point-goal episodes: the goal mark makes the semantic channel as low as -1 (navi_env.sim.goals)."""


def pointgoal_config(config: EnvConfig | None = None) -> EnvConfig:
    """`config` (default EnvConfig()) for point-goal episodes: task pointgoal, and episodes of
    POINTGOAL_EPISODE_STEPS when it keeps the exploring default length."""
    cfg = config or EnvConfig()
    steps = cfg.max_steps_per_episode
    if steps == EnvConfig().max_steps_per_episode:
        steps = POINTGOAL_EPISODE_STEPS
    return replace(cfg, task="pointgoal", max_steps_per_episode=steps)


OBS_HIGH = (1.0, 1.0, 1.0)
"""Highest value per channel."""


def make_batched_env(
    corpus: str | os.PathLike[str],
    num_envs: int,
    device: str | torch.device = "cpu",
    config: EnvConfig | None = None,
    obstacles: int = 0,
    squad: int = 0,
    max_episode_steps: int = 0,
    seed: int = 0,
) -> SdfDagEnv:
    """`num_envs` drones over the corpus folder's scenes (spawned at its qualified positions, with the
    obstacles its scenes declare), on `device`, writing its two observation buffers in turn. `obstacles` K > 0 gives every drone K scripted moving
    obstacles, `squad` G >= 2 makes squads of G drones that see each other (they replace
    config.obstacles' count and squad); `max_episode_steps` > 0 replaces config.max_steps_per_episode."""
    cfg = replace(config or EnvConfig(), obs_buffers=2)  # a step's observation outlives the next step
    if obstacles or squad:
        cfg = replace(cfg, obstacles=replace(cfg.obstacles, count=obstacles, squad=squad))
    if max_episode_steps > 0:
        cfg = replace(cfg, max_steps_per_episode=max_episode_steps)
    scenes, manifest = load_corpus_folder(corpus, torch.device(device))
    return SdfDagEnv(
        scenes,
        num_envs,
        scenes.device,
        cfg,
        manifest.spawn_tensors(),
        seed,
        scene_obstacles=manifest.obstacle_settings(),
    )


def obs_bounds(env: SdfDagEnv) -> tuple[torch.Tensor, torch.Tensor]:
    """(low, high) of one actor's observation, (3, Az, El) float32 each, on the host."""
    shape = env.obs_shape
    lowest = OBS_LOW_POINTGOAL if env.goal_marks else OBS_LOW
    low = torch.tensor(lowest, dtype=torch.float32)[:, None, None].expand(shape)  # (3, Az, El)
    high = torch.tensor(OBS_HIGH, dtype=torch.float32)[:, None, None].expand(shape)  # (3, Az, El)
    return low.contiguous(), high.contiguous()
