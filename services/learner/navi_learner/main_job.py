"""`navi run`: the main job. Build the procedural default corpus when missing, train a bounded budget
(resuming from the registry's latest when compatible), auto-promote, evaluate against the random and
reactive baselines on the same scenes, spawns and seeds, and write the comparison beside the report."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import torch

from navi_learner.baselines import EvalPolicy, RandomPolicy, ReactivePolicy
from navi_learner.checkpoint import CheckpointError, atomic_write, read_meta
from navi_learner.config import EngineConfig, TrainConfig, default_actors
from navi_learner.envs import EnvUnavailable, corpus_summary, make_env
from navi_learner.evaluate import CheckpointPolicy, comparison_table, evaluate
from navi_learner.registry import ModelRegistry
from navi_learner.train import train


class MainJobError(RuntimeError):
    """A piece the main job needs is missing."""


def ensure_corpus(corpus: Path, device: torch.device) -> None:
    """Build the procedural default corpus into `corpus` unless it already has a manifest. On a CPU the
    corpus is smaller (4 scenes at 128³) so that `make run` stays within minutes on 2 cores."""
    if (corpus / "manifest.json").is_file():
        return
    try:
        from navi_env.corpus import CorpusError, build_default_corpus
    except ImportError as err:
        raise MainJobError(
            f"no corpus at {corpus} and navi_env's corpus builder is not importable ({err})"
        ) from err
    count, resolution = (4, 128) if device.type == "cpu" else (16, 512)
    print(
        f"[navi run] building the procedural default corpus ({count} scenes, {resolution}^3) into {corpus}",
        flush=True,
    )
    try:
        build_default_corpus(
            corpus,
            resolution=resolution,
            count=count,
            device=device,
            progress=lambda line: print(f"[navi run] {line}", flush=True),
        )
    except CorpusError as err:
        raise MainJobError(f"building the default corpus failed: {err}") from err


def main_job(
    corpus: Path, total_steps: int, eval_steps: int, device: str, seed: int, models_dir: Path
) -> Path:
    """Returns the path of the training report."""
    dev = torch.device(device)
    ensure_corpus(corpus, dev)
    n = default_actors(dev)
    budget = total_steps or (6_144 if dev.type == "cpu" else 2_000_000)  # a few minutes on 2 cores
    rollout = 128 if dev.type == "cpu" else 0
    cfg = TrainConfig(n_actors=n, rollout_length=rollout, total_steps=budget, device=device, seed=seed)
    registry = ModelRegistry(models_dir)
    resume: Path | None = None
    if registry.latest_path.is_file():
        try:
            meta = read_meta(registry.latest_path)
            if meta.temporal_core == cfg.engine.temporal_core:
                resume = registry.latest_path
                cfg = TrainConfig(
                    **{**asdict(cfg), "engine": EngineConfig(**meta.config["engine"]), "ppo": cfg.ppo}
                )
                budget = meta.step_id + budget
                cfg.total_steps = budget
        except CheckpointError as err:
            print(f"[navi run] ignoring {registry.latest_path}: {err}", flush=True)
    try:
        env = make_env(corpus, n, device, seed)
    except EnvUnavailable as err:
        raise MainJobError(str(err)) from err
    print(f"[navi run] training {budget:,} steps on {device} with {n} actors", flush=True)
    result = train(
        env, cfg, resume_from=resume, registry=registry, corpus_summary=corpus_summary(corpus, "sdfdag")
    )
    print(
        f"[navi run] trained to step {result.step_id:,}, reward_ema {result.reward_ema:+.4f}; "
        f"promoted: {result.promoted or 'no (did not beat the best)'}",
        flush=True,
    )
    n_eval = min(n, 64)
    policies: list[EvalPolicy] = [
        CheckpointPolicy(result.final_checkpoint, dev),
        RandomPolicy(seed),
        ReactivePolicy(),
    ]
    rows = [
        evaluate(make_env(corpus, n_eval, device, seed), p, eval_steps, seed, progress=True) for p in policies
    ]
    rows[0].policy = f"trained ({result.run_id})"
    table = comparison_table(rows)
    reports = result.run_dir / "reports"
    text = f"# Evaluation of run {result.run_id}\n\n{eval_steps} steps x {n_eval} actors, seed {seed}.\n\n{table}\n"
    atomic_write(reports / "evaluation.md", lambda f: f.write(text.encode()))
    blob = json.dumps({"run_id": result.run_id, "results": [asdict(r) for r in rows]}, indent=2).encode()
    atomic_write(reports / "evaluation.json", lambda f: f.write(blob))
    print(table, flush=True)
    print(f"[navi run] evaluation: {reports / 'evaluation.md'}", flush=True)
    return result.report
