"""The batched env as the ecosystem adapters see it: built from a corpus folder with two observation
buffers written in turn (consecutive steps hand out distinct tensors, no copy), its bounds, and the
pooled view an MLP policy reads (`pool_view`, MLP_VIEW). Torch only (no RL library)."""

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


def obs_bounds(env: SdfDagEnv, view: tuple[int, int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(low, high) of one actor's observation, (3, Az, El) float32 each, on the host; (3, Az', El') for
    the pooled view `view` (pool_view keeps every channel within its bounds)."""
    shape = env.obs_shape if view is None else torch.Size((env.obs_shape[0], *view))
    lowest = OBS_LOW_POINTGOAL if env.goal_marks else OBS_LOW
    low = torch.tensor(lowest, dtype=torch.float32)[:, None, None].expand(shape)  # (3, Az, El)
    high = torch.tensor(OBS_HIGH, dtype=torch.float32)[:, None, None].expand(shape)  # (3, Az, El)
    return low.contiguous(), high.contiguous()


MLP_VIEW = (16, 4)
"""(Az', El') of the view the MLP adapters hand out by default: 3 x 16 x 4 = 192 inputs. An MLP over
the full 256 x 48 view has 36,864 inputs, and one Adam step (each weight moves by about the learning
rate) then shifts a first-layer unit by lr x the sum of its inputs' magnitudes, about 6 at lr 1e-3 from
the semantic channel alone (0.5 on every hit): every tanh unit saturates within the first update and
the policy's mean action stops depending on the observation (docs/ENVIRONMENT.md)."""


def view_of(env: SdfDagEnv, view: tuple[int, int] | None) -> tuple[int, int] | None:
    """The pooled view an adapter hands out for `view`: None (the env's own view, no pooling) when
    `view` is None or the env's view already is that size; raises when the env's bins do not split
    into it."""
    if view is None:
        return None
    az, el = env.obs_shape[1], env.obs_shape[2]
    if (az, el) == tuple(view):
        return None
    if view[0] < 1 or view[1] < 1 or az % view[0] or el % view[1]:
        raise ValueError(f"a {az} x {el} view does not pool into {view[0]} x {view[1]} blocks")
    return (int(view[0]), int(view[1]))


def pool_view(obs: torch.Tensor, view: tuple[int, int]) -> torch.Tensor:
    """The nearest ray of each block: obs (N, 3, Az, El) -> a new (N, 3, Az', El') tensor, Az' dividing
    Az and El' dividing El. Azimuth block a' is centred on bin a' x Az/Az' (block 0 straight ahead, as bin
    0 of a pattern traced at Az' bins), elevation block e' covers bins e' x El/El' onwards. Each pooled
    ray reads the block's smallest depth (channel 0: the nearest surface, so no obstacle thinner than a
    block disappears), that ray's semantic and delta depth (channels 1 and 2), and the goal mark where
    any ray of the block carries it (point-goal episodes paint it as a negative semantic value)."""
    n, c, az, el = obs.shape
    a, e = view
    ka, ke = az // a, el // e
    rolled = obs.roll(ka // 2, dims=2)  # (N, 3, Az, El): block 0 centred on straight ahead
    blocks = rolled.reshape(n, c, a, ka, e, ke).permute(0, 1, 2, 4, 3, 5).reshape(n, c, a, e, ka * ke)
    # blocks (N, 3, Az', El', K): the K = ka x ke rays of every block
    nearest = blocks[:, 0].argmin(dim=-1, keepdim=True)  # (N, Az', El', 1)
    pooled = blocks.gather(-1, nearest[:, None].expand(n, c, a, e, 1)).squeeze(-1)  # (N, 3, Az', El')
    mark = blocks[:, 1].amin(dim=-1)  # (N, Az', El') the lowest semantic value of the block
    pooled[:, 1] = torch.where(mark < 0.0, mark, pooled[:, 1])
    return pooled
