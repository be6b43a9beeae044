"""Environment factory: the drone env (navi_env.sim.env.SdfDagEnv over a corpus folder, imported lazily)
or the toy env."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import torch

from navi_learner.config import TrainConfig
from navi_learner.envs.protocol import BatchedEnv
from navi_learner.envs.toy import ToyEnv

if TYPE_CHECKING:
    from navi_env.config import RewardConfig

EnvKind = Literal["sdfdag", "toy"]


class EnvUnavailable(RuntimeError):
    """The drone environment (or its corpus) cannot be built here."""


def corpus_summary(corpus: Path | None, kind: EnvKind) -> dict[str, Any]:
    """Plain description of what a run trains on, for checkpoints and manifests."""
    if kind == "toy" or corpus is None:
        return {"kind": kind}
    try:
        from navi_env.corpus.folder import CorpusError, read_manifest
    except ImportError as err:
        raise EnvUnavailable(f"navi_env's corpus reader is not importable: {err}") from err
    try:
        manifest = read_manifest(corpus)
    except CorpusError as err:
        raise EnvUnavailable(str(err)) from err
    return {"kind": kind, "path": str(corpus), **manifest.summary()}


def reward_config(overrides: Mapping[str, float], task: str | None = None) -> RewardConfig:
    """The default RewardConfig with the named float fields replaced; ValueError names an unknown
    field or one that is not a float weight (exploration_table_bits is a size, not a weight), and, for
    a `task`, a collision weight that only the other task reads (RewardConfig.collision_price)."""
    from navi_env.config import COLLISION_WEIGHT, RewardConfig

    floats = {f.name for f in fields(RewardConfig) if f.type in ("float", float)}
    unknown = sorted(set(overrides) - floats)
    if unknown:
        raise ValueError(f"unknown reward weight(s) {', '.join(unknown)}; known: {', '.join(sorted(floats))}")
    if task in COLLISION_WEIGHT:
        own = COLLISION_WEIGHT[task]
        foreign = sorted(set(overrides) & (set(COLLISION_WEIGHT.values()) - {own}))
        if foreign:
            raise ValueError(f"{task} episodes do not read {foreign[0]}; their collision weight is {own}")
    values: dict[str, Any] = {k: float(v) for k, v in overrides.items()}
    return replace(RewardConfig(), **values)


def parse_reward_overrides(items: Sequence[str]) -> dict[str, float]:
    """KEY=VALUE strings (a CLI's --reward) as a dict, checked against RewardConfig."""
    out: dict[str, float] = {}
    for item in items:
        key, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--reward expects KEY=NUMBER, got {item!r}") from None
    reward_config(out)
    return out


def make_env(
    corpus: Path | None,
    n_actors: int,
    device: str,
    seed: int,
    kind: EnvKind = "sdfdag",
    episode_steps: int = 0,
    rank: int = 0,
    world: int = 1,
    scene: int | None = None,
    reward: Mapping[str, float] | None = None,
    obstacles: int = 0,
    squad: int = 0,
    task: str = "explore",
    rank_scenes: str = TrainConfig.rank_scenes,
) -> BatchedEnv:
    """Build N actors of the chosen environment on device (the drone env spawns at the corpus's
    qualified positions). `episode_steps` > 0 sets the drone env's episode length (evaluation). With
    world > 1 (data-parallel training) the drone env flies every scene (`rank_scenes` "all"), or only
    this rank's share with "share" (navi_env's `rank_share`), and with `scene` that scene of the corpus
    alone.
    `reward` replaces RewardConfig fields by name (see `reward_config`). `obstacles` > 0 gives every actor
    that many scripted moving obstacles (EnvConfig.obstacles, default motions and sizes); `squad` >= 2
    makes squads of that many actors share a scene and see and collide with each other. `task` is
    EnvConfig.task; point-goal episodes last POINTGOAL_EPISODE_STEPS unless `episode_steps` says."""
    if kind == "toy":
        return ToyEnv(n_actors, device, seed=seed)
    if corpus is None:
        raise EnvUnavailable("the drone environment needs --corpus DIR (a corpus folder with manifest.json)")
    if not corpus.is_dir():
        raise EnvUnavailable(f"corpus folder {corpus} does not exist (build one with `navi corpus build`)")
    try:
        from navi_env.config import POINTGOAL_EPISODE_STEPS, EnvConfig, ObstacleConfig
        from navi_env.corpus.folder import CorpusError, load_corpus_folder
        from navi_env.sim.env import SdfDagEnv
    except ImportError as err:
        raise EnvUnavailable(f"navi_env's SdfDagEnv is not importable: {err}") from err
    try:
        scenes, manifest = load_corpus_folder(corpus, torch.device(device), rank, world, scene, rank_scenes)
    except CorpusError as err:
        raise EnvUnavailable(str(err)) from err
    steps = episode_steps if episode_steps > 0 else POINTGOAL_EPISODE_STEPS if task == "pointgoal" else 0
    try:
        config = EnvConfig(task=task, max_steps_per_episode=steps) if steps else EnvConfig(task=task)
    except ValueError as err:
        raise EnvUnavailable(str(err)) from err
    if reward:
        config = replace(config, reward=reward_config(reward, task))
    if obstacles or squad:
        try:
            config = replace(config, obstacles=ObstacleConfig(count=obstacles, squad=squad))
        except ValueError as err:
            raise EnvUnavailable(str(err)) from err
    try:
        env: BatchedEnv = SdfDagEnv(
            scenes,
            n_actors,
            torch.device(device),
            config,
            manifest.spawn_tensors(),
            seed,
            scene_obstacles=manifest.obstacle_settings(),
        )
    except ValueError as err:  # a scene without goals in range, or classes that clash with the goal mark
        if task == "explore":
            raise
        raise EnvUnavailable(str(err)) from err
    return env
