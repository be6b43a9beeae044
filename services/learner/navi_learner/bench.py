"""`navi bench train`: env only / env + inference / env + training SPS and ms per stage, one JSON object."""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from navi_learner.config import TrainConfig, resolve
from navi_learner.heads import ACTION_DIM
from navi_learner.memory import EpisodicMemory
from navi_learner.policy import CognitiveMambaPolicy
from navi_learner.protocol import BatchedEnv
from navi_learner.train import train


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def env_only_sps(env: BatchedEnv, steps: int) -> float:
    """Steps/s of the env alone with random actions."""
    actions = torch.rand(env.n_actors, ACTION_DIM, device=env.device) * 2 - 1  # (N, 4)
    env.reset(seed=0)
    for _ in range(min(10, steps)):
        env.step(actions)
    _sync(env.device)
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(actions)
    _sync(env.device)
    return steps * env.n_actors / (time.perf_counter() - t0)


def inference_sps(env: BatchedEnv, cfg: TrainConfig, steps: int) -> float:
    """Steps/s of env + the full rollout-side engine (encoder, RND, memory, core step, heads), no learning."""
    device = env.device
    policy = CognitiveMambaPolicy(env.obs_shape, cfg.engine).to(device)
    policy.amp = cfg.amp and device.type == "cuda"
    if cfg.compile and device.type == "cuda":
        policy.encoder.compile(dynamic=False)
    memory = EpisodicMemory(
        env.n_actors, cfg.engine.memory_slots, cfg.engine.embed_dim, cfg.engine.memory_threshold, device
    )
    state = policy.initial_state(env.n_actors, device)
    obs = env.reset(seed=0)
    resets = torch.ones(env.n_actors, dtype=torch.bool, device=device)  # (N,)
    t0 = 0.0
    with torch.no_grad():
        for i in range(steps + 10):
            if i == 10:
                _sync(device)
                t0 = time.perf_counter()
            out = policy.act(obs, resets, state)
            policy.rnd.intrinsic(out.emb)
            memory.step(out.emb, resets)
            step = env.step(out.action)
            obs, resets, state = step.obs, step.done | step.truncated, out.state
    _sync(device)
    return steps * env.n_actors / (time.perf_counter() - t0)


def bench_train(
    env: BatchedEnv, cfg: TrainConfig, updates: int = 5, warmup: int = 2, env_steps: int = 50
) -> dict[str, Any]:
    """All three columns for one configuration; the training column skips `warmup` updates."""
    cfg = replace(resolve(cfg, env.obs_shape), sync_timers=True, log_every=1, checkpoint_every=10**12)
    per_update = cfg.n_actors * cfg.rollout_length
    cfg = replace(cfg, total_steps=per_update * (warmup + updates))
    device = env.device
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    out: dict[str, Any] = {
        "actors": cfg.n_actors,
        "rollout_length": cfg.rollout_length,
        "temporal_core": cfg.engine.temporal_core,
        "device": str(device),
        "obs_shape": list(env.obs_shape),
        "amp": cfg.amp and device.type == "cuda",
        "compile": cfg.compile and device.type == "cuda",
        "env_only_sps": round(env_only_sps(env, env_steps)),
        "env_inference_sps": round(inference_sps(env, cfg, env_steps)),
    }
    rows: list[dict[str, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        train(env, cfg, run_dir=Path(tmp) / "run", on_log=lambda _rid, row: rows.append(row), progress=False)
    measured = rows[warmup:] or rows
    mean = {
        k: sum(r[k] for r in measured) / len(measured) for k in ("sps", "ms_env", "ms_forward", "ms_learn")
    }
    out.update(
        {
            "env_train_sps": round(mean["sps"]),
            "ms_per_step": {k[3:]: round(mean[k], 3) for k in mean if k != "sps"},
        }
    )
    if device.type == "cuda":
        out["max_memory_gb"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
    return out
