"""`navi bench wrappers`: env-steps per second of the raw SdfDagEnv and of each ecosystem adapter over
the same env, in one job, under the same uniform random actions.

Variants over one env with two observation buffers (EnvConfig.obs_buffers=2, as the adapters build it):
raw (SdfDagEnv.step), gym (NaviVectorEnv, the default: final_obs from the env's previous buffer),
gym_no_final_obs (NaviVectorEnv(final_obs=False)), skrl (SkrlEnv), torchrl
(NaviTorchRLEnv.step_and_maybe_reset, what TorchRL's collectors call; it includes TorchRL's own work:
TensorDicts, step_mdp, the done check that reads the device once per step, and the merge of reset
observations into a new tensor), and raw_torchrl_copies (the raw step plus the observation copies
TorchRL's data model asks for: its collectors keep every step's tensors, so a new observation each step
and a second one, the next root, after a step where an episode ended; the least any TorchRL adapter
pays). Adapters whose library is not installed are left out. The
variants take turns, `repeats` rounds of `steps` timed steps each, and each reports its best round, so
a slow moment of the machine does not land on one variant only.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from importlib.util import find_spec
from pathlib import Path

import torch

from navi_env.config import EnvConfig
from navi_env.sim.env import SdfDagEnv

WARMUP_STEPS = 5
"""Untimed steps of each variant before its first round (the CUDA graph is recorded by the third)."""


def step_functions(env: SdfDagEnv, actions: torch.Tensor) -> dict[str, Callable[[], object]]:
    """variant -> a function that takes one step of `env` with the (N, 4) actions; each variant has
    been reset."""
    env.reset(seed=0)

    def torchrl_copies() -> object:
        """The raw step plus the observation tensors TorchRL's data keeps: a new one every step, a second
        after a step where an episode ended (read on the host, as TorchRL's done check does)."""
        out = env.step(actions)
        kept = [out.obs.clone()]  # (N, 3, Az, El)
        if bool(out.truncated.any()):
            kept.append(out.obs.clone())  # (N, 3, Az, El)
        return kept

    variants: dict[str, Callable[[], object]] = {
        "raw": lambda: env.step(actions),
        "raw_torchrl_copies": torchrl_copies,
    }
    if find_spec("gymnasium") is not None:
        from navi_env.ecosystem.gym import NaviVectorEnv

        gym_env = NaviVectorEnv(env)
        gym_env.reset(seed=0)
        variants["gym"] = lambda: gym_env.step(actions)
        lean = NaviVectorEnv(env, final_obs=False)
        lean.reset(seed=0)
        variants["gym_no_final_obs"] = lambda: lean.step(actions)
        if find_spec("skrl") is not None:
            from navi_env.ecosystem.skrl import SkrlEnv

            skrl_env = SkrlEnv(NaviVectorEnv(env), view=None)
            skrl_env.reset()
            variants["skrl"] = lambda: skrl_env.step(actions)
    if find_spec("torchrl") is not None:
        from navi_env.ecosystem.torchrl import NaviTorchRLEnv

        rl_env = NaviTorchRLEnv(env)
        carrier = [rl_env.reset()]

        def torchrl_step() -> object:
            td = carrier[0]
            td.set("action", actions)
            data, carrier[0] = rl_env.step_and_maybe_reset(td)
            return data

        variants["torchrl"] = torchrl_step
    return variants


def bench_wrappers(
    gmdag: Path | None,
    corpus: Path | None,
    actors: int,
    steps: int,
    device: str,
    azimuth: int,
    elevation: int,
    seed: int = 0,
    repeats: int = 3,
) -> dict[str, object]:
    """Time every variant over one env (see the module docstring); returns the bench JSON object:
    steps_per_s and ms_per_step per variant, and overhead_pct (the wrapper's extra time per step over
    the raw env's, in percent)."""
    from navi_bench.env import bench_scenes

    scenes, spawns = bench_scenes(gmdag, corpus, device)
    env = SdfDagEnv(
        scenes,
        actors,
        device,
        EnvConfig(azimuth_bins=azimuth, elevation_bins=elevation, obs_buffers=2),
        spawns,
        seed,
    )
    g = torch.Generator(device=env.device).manual_seed(seed)
    actions = torch.empty(actors, 4, device=env.device).uniform_(-1.0, 1.0, generator=g)  # (N, 4)
    variants = step_functions(env, actions)
    # episodes at every stage, as in training (so actors end at every step, not all at once)
    env.steps.random_(0, env.config.max_steps_per_episode, generator=g)
    sync = torch.cuda.synchronize if env.device.type == "cuda" else (lambda: None)
    for step in variants.values():
        for _ in range(WARMUP_STEPS):
            step()
    best = {name: float("inf") for name in variants}
    for _ in range(repeats):
        for name, step in variants.items():
            sync()
            t0 = time.perf_counter()
            for _ in range(steps):
                step()
            sync()
            best[name] = min(best[name], time.perf_counter() - t0)
    ended = torch.zeros((), dtype=torch.int64, device=env.device)  # () episodes ended over `steps` steps
    for _ in range(steps):
        ended += env.step(actions).truncated.sum()
    raw = best["raw"]
    return {
        "device": str(env.device),
        "actors": actors,
        "steps": steps,
        "repeats": repeats,
        "scenes": len(scenes),
        "obs_shape": [actors, *env.obs_shape],
        "threads": torch.get_num_threads(),
        "ended_per_step": round(int(ended) / steps, 2),  # how often TorchRL merges reset observations
        "steps_per_s": {k: round(actors * steps / s, 1) for k, s in best.items()},
        "ms_per_step": {k: round(1000.0 * s / steps, 4) for k, s in best.items()},
        "overhead_pct": {k: round(100.0 * (s - raw) / raw, 2) for k, s in best.items() if k != "raw"},
    }
