"""Origin samples: a launch samples each actor's origin once before its rays, and every ray that starts
there (t = 0) takes its first step from that record. The outputs, step counts included, must be those
of each ray sampling its origin itself, bit for bit, on the CPU and on CUDA, for actors in free space,
inside solid, on the cube's faces, outside the cube and at non-finite points, with and without
primitives, yaw and a ray order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from navi_env.rays import tiled_ray_order
from navi_env.tracer import primitives as obstacles
from navi_env.tracer import trace as trace_module
from navi_env.tracer.abi import ORIGIN_SAMPLE_BYTES, check_layout
from navi_env.tracer.analytic_scenes import AnalyticScene, free_points, leaf_kind_scenes, random_directions
from navi_env.tracer.scene import SceneCorpus, load_corpus
from navi_env.tracer.trace import cpu_launcher, trace
from navi_env.tracer.trace_ref import trace_ref

R = 256  # rays per actor (a 16 x 16 pattern, so that tiled_ray_order applies)


def _corpus(device: str) -> SceneCorpus:
    """The scenes, each brick labelled with its own class (1 + index mod 7), so that a hit's semantic
    tells which brick the walk sampled last."""
    corpus = load_corpus([s.gmdag() for s in leaf_kind_scenes()], device)
    n = len(corpus.brick_class)
    corpus.brick_class.copy_((torch.arange(n) % 7 + 1).to(torch.uint8))  # (Nb,) uint8
    return corpus


def _actors(scenes: list[AnalyticScene]) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) scene ids and (B, 3) origins: free points of every scene, then the odd ones of scene 0."""
    ids, points = [], []
    for i, s in enumerate(scenes):
        points.append(free_points(s, 6, 0.0, seed=50 + i))  # (6, 3)
        ids += [i] * 6
    size = 32 * (8.0 / 32)  # demo_room(32, 8.0): 32 cells of 0.25 m from the origin 0
    odd = np.array(
        [
            [0.0, 3.0, 2.0],  # on the cube's low x face
            [size, 4.0, 4.0],  # on its high x face
            [4.0, 4.0, -2.0],  # below the cube: rays start at their entry times, or miss
            [-0.5, -0.5, 9.0],  # outside on two axes
            [np.nan, 1.0, 1.0],  # non-finite
            [4.0, 4.0, 0.05],  # in the floor slab (solid) or just above it
        ]
    )
    points.append(odd)
    ids += [0] * len(odd)
    return torch.tensor(ids), torch.tensor(np.concatenate(points), dtype=torch.float32)


def _trace(
    corpus: SceneCorpus,
    ids: torch.Tensor,
    origins: torch.Tensor,
    origin_pass: bool,
    prims: torch.Tensor | None,
) -> tuple[torch.Tensor, ...]:
    dev = corpus.device
    b = len(ids)
    dirs = torch.tensor(random_directions(R, seed=7), dtype=torch.float32, device=dev)  # (R, 3)
    yaw = torch.linspace(0.0, 6.0, b, device=dev)  # (B,)
    depth = torch.full((b, R), -1.0, device=dev)  # (B, R) float32
    sem = torch.full((b, R), -1, dtype=torch.int32, device=dev)  # (B, R) int32
    steps = torch.full((b, R), -1, dtype=torch.int32, device=dev)  # (B, R) int32
    before = trace_module._ORIGIN_PASS
    trace_module._ORIGIN_PASS = origin_pass
    try:
        trace(
            corpus, ids.to(dev), origins.to(dev), dirs, yaw=yaw, out_depth=depth, out_semantic=sem,
            out_steps=steps, ray_order=tiled_ray_order(16, 16).to(dev), hit_slope=0.01, prims=prims,
        )  # fmt: skip
    finally:
        trace_module._ORIGIN_PASS = before
    return depth.nan_to_num(-7.0).cpu(), sem.cpu(), steps.cpu()


def _check(device: str) -> None:
    corpus = _corpus(device)
    ids, origins = _actors(leaf_kind_scenes())
    gen = torch.Generator().manual_seed(3)
    prims = obstacles.scatter(origins.nan_to_num(), 4, gen, near=0.5, far=3.0).to(device)  # (B, 4, 16)
    for p in (None, prims):
        once = _trace(corpus, ids, origins, True, p)
        per_ray = _trace(corpus, ids, origins, False, p)
        for a, b in zip(once, per_ray, strict=True):
            assert torch.equal(a, b)
        assert float((once[1] > 0).float().mean()) > 0.3  # most rays end on a surface
        assert len(set(once[1].unique().tolist()) - {0}) >= 3  # on bricks of several classes
        assert bool((once[2][:18] >= 1).all())  # the free actors' rays all took their first step


def test_origin_samples_change_nothing_on_the_cpu() -> None:
    _check("cpu")


def test_origin_samples_keep_the_reference_parity() -> None:
    """trace_ref samples every ray's origin itself: the launch with origin samples matches it."""
    corpus = _corpus("cpu")
    ids, origins = _actors(leaf_kind_scenes())
    dirs = torch.tensor(random_directions(R, seed=8), dtype=torch.float32)  # (R, 3)
    out = []
    for fn in (trace, trace_ref):
        depth = torch.full((len(ids), R), -1.0)  # (B, R) float32
        sem = torch.full((len(ids), R), -1, dtype=torch.int32)  # (B, R) int32
        steps = torch.full((len(ids), R), -1, dtype=torch.int32)  # (B, R) int32
        fn(corpus, ids, origins, dirs, out_depth=depth, out_semantic=sem, out_steps=steps, hit_slope=0.01)
        out.append((depth.nan_to_num(-7.0), sem, steps))
    for a, b in zip(*out, strict=True):
        assert torch.equal(a, b)
    assert len(set(out[0][1].unique().tolist()) - {0}) >= 3  # hits on bricks of several classes


def test_origin_record_size_matches_the_build() -> None:
    # The launch allocates ORIGIN_SAMPLE_BYTES per actor for records the build writes at its own size.
    assert cpu_launcher().origin_sample_size() == ORIGIN_SAMPLE_BYTES


def test_a_stale_origin_record_size_is_refused() -> None:
    lib = cpu_launcher()
    with pytest.raises(RuntimeError, match=r"sizeof\(OriginSample\) is 48 bytes.*expects 80"):
        check_layout(
            lib.trace_args_size, lib.sample_args_size, lib.sweep_args_size, lambda: 48, "a stale build"
        )


@pytest.mark.gpu
@pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is false)"
)
def test_origin_samples_change_nothing_on_cuda() -> None:
    _check("cuda")
