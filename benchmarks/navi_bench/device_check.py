"""One check of the tracer on a CUDA host: `python -m navi_bench.device_check [--gmdag FILE ...]`.

1. Builds the CUDA launchers (nvcc) and prints ptxas' register / stack / spill report.
2. CUDA vs CPU parity (trace with yaw, sample_distance) on analytic scenes, including thin walls.
3. CUDA accuracy against exact analytic hits on a 256^3 room.
4. Times `trace` at 1k / 4k / 8k agents x 256x48 rays on each --gmdag (default: the 256^3 room).
Prints a table last; writes device_check.json under $OUT when that is set.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from navi_bench.trace import TraceBenchConfig, TraceBenchResult, bench_trace
from navi_env.tracer import analytic_scenes as analytic
from navi_env.tracer.cuda_build import CSRC, NVCC_FLAGS, build_library, cuda_library, find_nvcc
from navi_env.tracer.scene import SceneCorpus, load_corpus, load_scene
from navi_env.tracer.trace import sample_distance, trace

AGENT_COUNTS = (1024, 4096, 8192)
REL_TOL = 1e-4


def say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def ptxas_report() -> str:
    """ptxas -v lines of the trace kernel (registers, stack frame, spills)."""
    cmd = [find_nvcc(), *[f for f in NVCC_FLAGS if f != "-shared"], "-c", "-Xptxas=-v", f"-I{CSRC}",
           "-o", os.devnull, str(CSRC / "trace_cuda.cu")]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stderr
    lines = out.splitlines()
    keep = [
        ln.strip()
        for i, ln in enumerate(lines)
        if ("Used" in ln or "stack frame" in ln)
        and any("trace_kernel" in p for p in lines[max(0, i - 3) : i + 1])
    ]
    return " | ".join(keep)


def parity_scenes() -> list[analytic.AnalyticScene]:
    return [
        analytic.demo_room(64, 16.0),
        analytic.AnalyticScene(
            (analytic.Sphere((5.1, 4.3, 3.9), 2.6), analytic.Box((0.5, 0.5, 0.5), (3.0, 7.0, 2.0))), 64, 0.125
        ),
        analytic.slab_scene(0.25, np.array([0.3, -0.2, 0.9]), resolution=64),
    ]


def parity(cpu: SceneCorpus, cuda: SceneCorpus, scenes: list[analytic.AnalyticScene]) -> dict[str, float]:
    """CUDA vs CPU over 64 agents per scene x 2048 rays with yaw; and sample_distance."""
    per = 64
    origins = np.concatenate(
        [analytic.free_points(s, per, 0.0, seed=i) for i, s in enumerate(scenes)]
    )  # (B, 3)
    ids = torch.arange(len(scenes)).repeat_interleave(per)  # (B,)
    o = torch.tensor(origins, dtype=torch.float32)  # (B, 3)
    dirs = torch.tensor(analytic.random_directions(2048, seed=1), dtype=torch.float32)  # (R, 3)
    yaw = torch.linspace(-3.0, 3.0, len(ids))  # (B,)
    out = {}
    d_cpu, s_cpu = torch.empty(len(ids), 2048), torch.empty(len(ids), 2048, dtype=torch.int32)
    trace(cpu, ids, o, dirs, yaw=yaw, out_depth=d_cpu, out_semantic=s_cpu)
    d_gpu = torch.empty(len(ids), 2048, device="cuda")  # (B, R) float32
    s_gpu = torch.empty(len(ids), 2048, dtype=torch.int32, device="cuda")  # (B, R) int32
    trace(cuda, ids.cuda(), o.cuda(), dirs.cuda(), yaw=yaw.cuda(), out_depth=d_gpu, out_semantic=s_gpu)
    diff = (d_gpu.cpu() - d_cpu).abs()  # (B, R)
    out["trace_rays"] = float(diff.numel())
    out["trace_identical_fraction"] = float((diff == 0).float().mean())
    out["trace_within_1e-4_fraction"] = float((diff <= REL_TOL * d_cpu.abs().clamp(min=1e-3)).float().mean())
    out["trace_max_abs_diff_m"] = float(diff.max())
    out["semantic_mismatch_fraction"] = float((s_gpu.cpu() != s_cpu).float().mean())
    pts = torch.tensor(np.concatenate([analytic.free_points(s, 2000, -1e9, seed=9 + i) for i, s in enumerate(scenes)]),
                       dtype=torch.float32)  # fmt: skip
    sid = torch.arange(len(scenes)).repeat_interleave(2000)  # (N,)
    sd = (sample_distance(cuda, sid.cuda(), pts.cuda()).cpu() - sample_distance(cpu, sid, pts)).abs()
    out["sample_max_abs_diff_m"] = float(sd.max())
    return out


def room_accuracy(scene: analytic.AnalyticScene, corpus: SceneCorpus) -> dict[str, float]:
    """CUDA trace vs exact hits in the analytic room (voxels)."""
    origins = analytic.free_points(scene, 64, 0.3, seed=3)  # (B, 3)
    dirs = analytic.random_directions(2048, seed=4)  # (R, 3)
    depth = torch.empty(64, 2048, device="cuda")  # (B, R) float32
    trace(corpus, torch.zeros(64, dtype=torch.int64, device="cuda"), torch.tensor(origins, dtype=torch.float32).cuda(),
          torch.tensor(dirs, dtype=torch.float32).cuda(), out_depth=depth, horizon=1000.0, max_steps=2048)  # fmt: skip
    exact = scene.hit(np.repeat(origins, 2048, axis=0), np.tile(dirs, (64, 1)))  # (B*R,)
    err = np.abs(depth.cpu().numpy().reshape(-1) - exact) / scene.voxel_size  # voxels
    return {"median_error_voxels": float(np.median(err)), "p95_error_voxels": float(np.quantile(err, 0.95))}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--gmdag", type=Path, action="append", default=[], help="scene(s) to time")
    parser.add_argument("--launches", type=int, default=20, help="timed launches per configuration")
    parser.add_argument(
        "--agents", type=int, action="append", default=[], help="agent counts (default 1k/4k/8k)"
    )
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("device_check needs a CUDA device (torch.cuda.is_available() is False)")
    report: dict[str, object] = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__}
    t0 = time.perf_counter()
    build_library()
    cuda_library()
    report["build_seconds"] = time.perf_counter() - t0
    report["ptxas"] = ptxas_report()
    say(f"ptxas: {report['ptxas']}")

    scenes = parity_scenes()
    gmdags = [s.gmdag(dilate_voxels=0.5 if i == 2 else 0.0) for i, s in enumerate(scenes)]
    report["parity"] = parity(load_corpus(gmdags), load_corpus(gmdags, "cuda"), scenes)
    say(f"parity: {report['parity']}")
    room = analytic.demo_room(256, 16.0)
    say("building the 256^3 analytic room")
    room_corpus = load_scene(room.gmdag(spawns=analytic.free_points(room, 64, 1.0, seed=5)), "cuda")
    report["room256_accuracy"] = room_accuracy(room, room_corpus)
    say(f"accuracy: {report['room256_accuracy']}")

    timing_sources: list[tuple[str, SceneCorpus]] = []
    for path in args.gmdag:
        timing_sources.append((path.name, load_scene(path, "cuda")))
    if not timing_sources:
        timing_sources.append(("analytic room 256^3", room_corpus))
    rows: list[tuple[str, TraceBenchResult]] = []
    for name, corpus in timing_sources:
        for agents in args.agents or AGENT_COUNTS:
            r = bench_trace(corpus, TraceBenchConfig(agents=agents, device="cuda", launches=args.launches))
            rows.append((name, r))
            say(f"{name} agents={agents}: {r.grays_per_s:.2f} G rays/s")
    report["timings"] = [{"source": name, **dataclasses.asdict(r)} for name, r in rows]
    out_dir = os.environ.get("OUT")
    if out_dir:
        Path(out_dir, "device_check.json").write_text(json.dumps(report, indent=2))
    p = report["parity"]
    assert isinstance(p, dict)
    print(f"\nGPU {report['gpu']}  build {report['build_seconds']:.1f}s  ptxas {report['ptxas']}")
    print(f"parity CUDA vs CPU: identical {p['trace_identical_fraction']:.4%}, within 1e-4 "
          f"{p['trace_within_1e-4_fraction']:.4%}, max |diff| {p['trace_max_abs_diff_m']:.3g} m, "
          f"semantic mismatch {p['semantic_mismatch_fraction']:.4%}, sample max |diff| {p['sample_max_abs_diff_m']:.3g} m")  # fmt: skip
    acc = report["room256_accuracy"]
    assert isinstance(acc, dict)
    print(
        f"room 256^3 accuracy: median {acc['median_error_voxels']:.3f} vox, p95 {acc['p95_error_voxels']:.3f} vox"
    )
    print(
        f"{'scene':<28}{'res':>5}{'agents':>8}{'ms':>9}{'Grays/s':>9}{'obs/s':>11}{'steps':>7}{'p99':>6}{'MiB':>8}"
    )
    for name, r in rows:
        print(
            f"{name[:27]:<28}{r.resolution:>5}{r.agents:>8}{r.ms_per_launch:>9.2f}{r.grays_per_s:>9.2f}"
            f"{r.observations_per_s:>11.0f}{r.mean_steps:>7.1f}{r.p99_steps:>6.0f}{r.bytes_per_scene / 2**20:>8.2f}"
        )


if __name__ == "__main__":
    main()
