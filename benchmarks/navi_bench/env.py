"""`navi bench env`: env-steps per second of SdfDagEnv under uniform random actions, and ms per stage."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from navi_env.tracer.scene import SceneCorpus


def bench_scenes(
    gmdag: Path | None, corpus: Path | None, device: str
) -> tuple[SceneCorpus, list[torch.Tensor] | None]:
    """The scenes a benchmark flies, on `device`: one .gmdag file, or a corpus folder and its qualified
    spawns (per scene, (S, 3) world meters)."""
    from navi_env.corpus.folder import load_corpus_folder
    from navi_env.tracer.scene import load_scene

    if corpus is not None:
        scenes, manifest = load_corpus_folder(corpus, device)
        return scenes, manifest.spawn_tensors()
    if gmdag is not None:
        return load_scene(gmdag, device), None
    raise ValueError("give a .gmdag file or a corpus folder")


def bench_env(
    gmdag: Path | None,
    corpus: Path | None,
    actors: int,
    steps: int,
    device: str,
    azimuth: int,
    elevation: int,
    seed: int,
    obstacles: int = 0,
    squad: int = 0,
) -> dict[str, object]:
    """Step SdfDagEnv `steps` times with uniform random actions; returns the bench JSON object. With
    `obstacles` K > 0 every actor has K scripted moving obstacles (their collisions and the share of rays
    that hit them are reported)."""
    import time

    import torch

    from navi_env.config import EnvConfig, ObstacleConfig
    from navi_env.sim.env import SdfDagEnv, StageTimer

    scenes, spawns = bench_scenes(gmdag, corpus, device)
    config = EnvConfig(
        azimuth_bins=azimuth, elevation_bins=elevation, obstacles=ObstacleConfig(count=obstacles, squad=squad)
    )
    env = SdfDagEnv(scenes, actors, device, config, spawns, seed)
    g = torch.Generator(device=env.device).manual_seed(seed)
    env.reset(seed=seed)
    actions = torch.empty(actors, 4, device=env.device)  # (N, 4)
    for _ in range(5):
        env.step(actions.uniform_(-1.0, 1.0, generator=g))
    sync = torch.cuda.synchronize if env.device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(actions.uniform_(-1.0, 1.0, generator=g))
    sync()
    seconds = time.perf_counter() - t0
    env.timer = StageTimer(env.device)  # a second, timed pass for the per-stage split
    hit_obstacle = torch.zeros((), device=env.device)  # () rays that hit an obstacle, summed over steps
    struck = torch.zeros((), device=env.device)  # () collisions with obstacles
    bumped = torch.zeros((), device=env.device)  # () collisions between drones
    for _ in range(steps):
        out = env.step(actions.uniform_(-1.0, 1.0, generator=g))
        hit_obstacle += (env.semantic == config.obstacles.semantic_class + 1).sum()
        struck += out.info["obstacle_collision"].sum()
        bumped += out.info["drone_collision"].sum()
    per_stage = {k: round(v / steps, 4) for k, v in env.timer.totals_ms().items()}
    extra: dict[str, object] = {}
    if squad >= 2:
        extra["squad"] = squad
        extra["drone_collisions_per_1k"] = round(1000.0 * float(bumped) / (steps * actors), 3)
    if obstacles:
        extra |= {
            "obstacle_hit_fraction": round(float(hit_obstacle) / (steps * actors * config.rays), 5),
            "obstacle_collisions_per_1k": round(1000.0 * float(struck) / (steps * actors), 3),
        }
    return {
        "device": str(env.device),
        "actors": actors,
        "steps": steps,
        "scenes": len(scenes),
        "steps_per_s": round(actors * steps / seconds, 1),
        "ms_per_step": round(1000.0 * seconds / steps, 4),
        "ms_per_stage": per_stage,
        "bytes_per_actor": env.bytes_per_actor(),
        "obs_shape": [actors, *env.obs_shape],
        "threads": torch.get_num_threads(),
        "obstacles_per_actor": obstacles,
        **extra,
    }
