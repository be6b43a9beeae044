"""`navi bench train`: env only / env + inference / env + training SPS and ms per stage, one JSON object.

`--nproc N` measures one process first, then N data-parallel ranks through torchrun (each rank with
the same actors on its own device, the three columns measured on every rank at once), then by default
one process again, and reports the per-rank and total SPS with the scaling efficiency SPS(N) / (N x
SPS(1)) of each column against the faster of the one-process runs (the one-process figure moves between
runs on some hosts, and the faster one gives the lower ratio), and every rank's timeline of a training
step (collect, forward, update, sync: what it waits for the others).

`--versus OPTIONS` measures the command as given (the base) and the same with OPTIONS added (the
variant), each run in a process of its own, in turn for `--rounds` rounds, and reports both medians and
their ratio: a lever judged against its base in one job.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import torch

from navi_bench.profile import profile_stages
from navi_learner.config import TrainConfig, compact_storage, resolve
from navi_learner.engine.heads import ACTION_DIM
from navi_learner.engine.memory import EpisodicMemory
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.envs.protocol import BatchedEnv, capabilities
from navi_learner.ppo.compile import make_forward, update_graphs
from navi_learner.ppo.dist import Dist, Sync, entry_argv, relaunch
from navi_learner.ppo.train import train


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


def inference_sps(
    env: BatchedEnv,
    cfg: TrainConfig,
    steps: int,
    sync: Sync | None = None,
) -> float:
    """Steps/s of env + the full rollout-side engine (encoder, RND, memory, core step, heads), no learning;
    on a data-parallel rank (`sync`) the RND normaliser is pooled over ranks as training pools it."""
    device = env.device
    policy = CognitiveMambaPolicy(env.obs_shape, cfg.engine).to(device)
    policy.amp = cfg.amp and device.type == "cuda"
    if cfg.compile and device.type == "cuda":
        policy.encoder.compile(dynamic=False)
    memory = EpisodicMemory(
        env.n_actors, cfg.engine.memory_slots, cfg.engine.embed_dim, cfg.engine.memory_threshold, device
    )
    forward = make_forward(policy, memory, cfg, device, sync)
    state = policy.initial_state(env.n_actors, device)
    obs = env.reset(seed=0)
    resets = torch.ones(env.n_actors, dtype=torch.bool, device=device)  # (N,)
    t0 = 0.0
    with torch.no_grad():
        for i in range(steps + 10):
            if i == 10:
                _sync(device)
                t0 = time.perf_counter()
            out, _, _ = forward(obs, resets, state)
            step = env.step(out.action)
            obs, resets, state = step.obs, step.done | step.truncated, out.state
    _sync(device)
    return steps * env.n_actors / (time.perf_counter() - t0)


def bench_train(
    env: BatchedEnv,
    cfg: TrainConfig,
    updates: int = 5,
    warmup: int = 2,
    env_steps: int = 50,
    dist: Dist | None = None,
    profile_dir: Path | None = None,
) -> dict[str, Any]:
    """All three columns for one configuration; the training column skips `warmup` updates.

    On a rank of a data-parallel run (`dist`) every rank measures its own columns, all ranks starting
    each column together; every rank returns {"world_size", "ranks": [each rank's columns], "total"}.
    Besides the columns: ms per env step of each stage (`ms_per_step`, stages exclusive of the sync
    within them) and the step's timeline (`timeline_ms`).

    With `profile_dir` one more update runs after the measured ones, its rollout and its update under
    torch.profiler (navi_bench.profile: one file per stage and rank in `profile_dir`)."""
    d = dist or Dist()
    sync = Sync(d, [], env.device) if d.active else None
    compact = compact_storage(cfg, bool(getattr(env, "compact_obs", False)))
    cfg = replace(
        resolve(cfg, env.obs_shape, compact), sync_timers=True, log_every=1, checkpoint_every=10**12
    )
    per_update = cfg.n_actors * cfg.rollout_length
    extra = 1 if profile_dir is not None else 0  # the profiled update, after the measured ones
    cfg = replace(cfg, total_steps=per_update * d.world * (warmup + updates + extra))  # every rank's steps
    device = env.device
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    out: dict[str, Any] = {
        "actors": cfg.n_actors,
        "rollout_length": cfg.rollout_length,
        "temporal_core": cfg.engine.temporal_core,
        "device": str(device),
        "obs_shape": list(env.obs_shape),
        "obs_storage": "compact" if compact else "float32",
        "max_minibatch": cfg.ppo.max_minibatch,
        "amp": cfg.amp and device.type == "cuda",
        "compile": cfg.compile and device.type == "cuda",
        "compile_rollout": cfg.compile and cfg.compile_rollout and device.type == "cuda",
        "compile_update": cfg.compile and cfg.compile_update and device.type == "cuda",
        "update_graphs": update_graphs(cfg, device),
        "tf32": cfg.tf32 and device.type == "cuda",
        "scenes": len(capabilities(env).scenes),  # this rank's (its share, or all with rank_scenes all)
        "rank_scenes": cfg.rank_scenes if d.active else "all",
    }
    if sync is not None:
        sync.barrier()
    out["env_only_sps"] = round(env_only_sps(env, env_steps))
    if sync is not None:
        sync.barrier()
    out["env_inference_sps"] = round(inference_sps(env, cfg, env_steps, sync))
    if sync is not None:
        sync.barrier()  # the normaliser's last sums waited for; every rank starts training together
    rows: list[dict[str, float]] = []
    tag = f"rank{d.rank}" if d.active else "one-process"
    profiling = (
        profile_stages(profile_dir, warmup + updates + 1, tag) if profile_dir is not None else nullcontext()
    )
    with tempfile.TemporaryDirectory() as tmp, profiling:
        train(
            env,
            cfg,
            run_dir=Path(tmp) / "run",
            on_log=lambda _rid, row: rows.append(row),
            progress=False,
            dist=d,
        )
    measured = rows[warmup : warmup + updates] or rows
    mean = {
        k: sum(r[k] for r in measured) / len(measured)
        for k in ("sps", "ms_env", "ms_forward", "ms_learn", "ms_sync")
    }
    ms = {k[3:]: round(mean[k], 3) for k in mean if k != "sps"}
    step_ms = sum(1000.0 * cfg.n_actors * d.world / r["sps"] for r in measured) / len(measured)  # per row
    out.update(
        {
            "env_train_sps": round(mean["sps"] / d.world),  # this rank's actor-steps/s (its own clock)
            "ms_per_step": ms,
            "timeline_ms": timeline(ms, step_ms),
        }
    )
    if device.type == "cuda":
        out["max_memory_gb"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
    if sync is None:
        return out
    ranks = sync.gather_object({"rank": d.rank, **out})
    return {"world_size": d.world, "ranks": ranks, "total": {k: sum(r[k] for r in ranks) for k in COLUMNS}}


COLUMNS = ("env_only_sps", "env_inference_sps", "env_train_sps")
"""The three SPS columns of `navi bench train`."""
TIMELINE = ("collect", "forward", "update", "sync", "other", "step")
"""A rank's training step, ms per env step: collect (the env step: physics, trace, observation, reward),
forward (the policy's act, RND and memory), update (advantages and the PPO update), each without the
time it waits in collectives, which is sync; other, the rest of the step's wall time (host work between
the stages, the log line); step, the wall time of one env step of this rank's actors."""


def timeline(ms: dict[str, float], step_ms: float) -> dict[str, float]:
    """A rank's TIMELINE from its stage times (`ms_per_step`: env, forward, learn, sync, exclusive) and
    the wall ms per env step of its actors."""
    parts = {"collect": ms["env"], "forward": ms["forward"], "update": ms["learn"], "sync": ms["sync"]}
    return {**parts, "other": round(step_ms - sum(parts.values()), 3), "step": round(step_ms, 3)}


def timeline_table(report: dict[str, Any]) -> str:
    """The scaling report's timelines as a table: one process (the baseline run), then each rank, ms per
    env step; then every one-process run's train SPS where there were several."""
    head = f"{'':>8}" + "".join(f"{k:>10}" for k in TIMELINE) + f"{'train SPS':>12}"
    lines = ["ms per env step: collect, forward and update without their waits; sync, the waits", head]
    for name, r in [("single", report["single"]), *((f"rank {r['rank']}", r) for r in report["ranks"])]:
        t = r["timeline_ms"]
        lines.append(
            f"{name:>8}" + "".join(f"{t[k]:>10.3f}" for k in TIMELINE) + f"{r['env_train_sps']:>12,}"
        )
    runs = report["single_runs"]
    if len(runs) > 1:
        each = " and ".join(f"{r['env_train_sps']:,}" for r in runs)
        lines.append(f"one process before and after the ranks: {each} train SPS (the faster is the baseline)")
    return "\n".join(lines)


def scaling_report(nproc: int, singles: list[dict[str, Any]], ranks: dict[str, Any]) -> dict[str, Any]:
    """The one-process runs' columns and nproc ranks' (per rank and total) joined, with the scaling
    efficiency of each column: total SPS(N) / (N x SPS(1)), SPS(1) the one-process run with the most
    train SPS ("single"; every run in "single_runs", in order). Every entry of "ranks" (and "single")
    keeps its timeline_ms."""
    if not singles:
        raise ValueError("scaling needs at least one one-process run")
    single = max(singles, key=lambda r: r["env_train_sps"])
    total = ranks["total"]
    return {
        "nproc": nproc,
        "single": single,
        "single_runs": singles,
        "ranks": ranks["ranks"],
        "total": total,
        "scaling_efficiency": {
            k.removesuffix("_sps"): round(total[k] / (nproc * single[k]), 3) if single[k] > 0 else None
            for k in COLUMNS
        },
    }


def one_process(args: list[str], path: Path, what: str) -> dict[str, Any]:
    """`navi bench train ARGS` in a process of its own, its result read from `path` (--result-file)."""
    cmd = [sys.executable, *entry_argv(), *args, "--result-file", str(path)]
    if subprocess.run(cmd, check=False).returncode != 0 or not path.is_file():
        raise RuntimeError(f"the {what} failed (its error is above)")
    return cast(dict[str, Any], json.loads(path.read_text()))


def bench_train_scaling(nproc: int, args: list[str], singles: int = 2) -> dict[str, Any]:
    """`navi bench train ARGS` as one process, then on nproc ranks through torchrun, then (`singles` 2)
    as one process again: one job, run one after the other so they do not share devices; ARGS is the
    command line without --nproc. The timelines' table goes to stderr."""
    if singles not in (1, 2):
        raise ValueError(f"singles must be 1 or 2, got {singles}")
    with tempfile.TemporaryDirectory() as tmp:
        ranks_file = Path(tmp) / "ranks.json"

        def single(k: int) -> dict[str, Any]:
            return one_process(args, Path(tmp) / f"single{k}.json", "one-process measurement")

        runs = [single(0)]
        code = relaunch(nproc, [*args, "--result-file", str(ranks_file)])
        if code != 0 or not ranks_file.is_file():
            raise RuntimeError(
                f"the {nproc}-rank measurement failed with exit code {code} (its error is above)"
            )
        runs += [single(k) for k in range(1, singles)]
        report = scaling_report(nproc, runs, json.loads(ranks_file.read_text()))
    print(timeline_table(report), file=sys.stderr, flush=True)
    return report


def versus_report(
    variant: list[str], base: list[dict[str, Any]], other: list[dict[str, Any]]
) -> dict[str, Any]:
    """The runs of the base command and of the variant (the base with `variant`'s options added), in
    run order, with each one's median train SPS and the ratio variant / base of the medians."""
    if not base or len(base) != len(other):
        raise ValueError("a comparison needs as many variant runs as base runs, at least one")
    medians = {
        name: statistics.median(r["env_train_sps"] for r in runs)
        for name, runs in (("base", base), ("variant", other))
    }
    return {
        "versus": " ".join(variant),
        "rounds": len(base),
        "base": base,
        "variant": other,
        "median_train_sps": medians,
        "ratio": round(medians["variant"] / medians["base"], 4),
    }


def versus_table(report: dict[str, Any]) -> str:
    """The comparison's runs as a table (train SPS and the update's ms per step, in run order)."""
    lines = [f"base against variant ({report['versus']}), in turn:"]
    for k, (a, b) in enumerate(zip(report["base"], report["variant"], strict=True), start=1):
        lines.append(
            f"  round {k}: base {a['env_train_sps']:,} SPS (update {a['timeline_ms']['update']:.2f} ms), "
            f"variant {b['env_train_sps']:,} SPS (update {b['timeline_ms']['update']:.2f} ms)"
        )
    m = report["median_train_sps"]
    lines.append(
        f"median train SPS: base {m['base']:,}, variant {m['variant']:,}: variant / base {report['ratio']}"
    )
    return "\n".join(lines)


def bench_train_versus(args: list[str], variant: list[str], rounds: int = 2) -> dict[str, Any]:
    """`navi bench train ARGS` (the base) and the same with `variant`'s options added, each run in a
    process of its own, base and variant in turn for `rounds` rounds: one job, so that both meet the
    host's conditions alike (one process's speed moves between jobs on some hosts). The runs' table goes
    to stderr."""
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1, got {rounds}")
    base: list[dict[str, Any]] = []
    other: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):
            base.append(one_process(args, Path(tmp) / f"base{k}.json", "base run"))
            other.append(one_process([*args, *variant], Path(tmp) / f"variant{k}.json", "variant run"))
    report = versus_report(variant, base, other)
    print(versus_table(report), file=sys.stderr, flush=True)
    return report
