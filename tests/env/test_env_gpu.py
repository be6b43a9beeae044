"""The CUDA environment agrees with the CPU one on a short rollout (needs a CUDA device)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch

from navi_compiler.dag.build import build_gmdag
from navi_env.config import EnvConfig, ObstacleConfig, SensorConfig
from navi_env.sim.env import SdfDagEnv
from navi_env.sim.observation import observe, observe_ref, semantic_table
from navi_env.tracer.scene import load_corpus

pytestmark = pytest.mark.gpu
needs_cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is false)"
)

RES, VOXEL = 32, 0.5


def room() -> object:
    i = np.arange(RES + 1, dtype=np.float64) * VOXEL
    p = np.stack(np.meshgrid(i, i, i, indexing="ij"), axis=-1)
    q = np.abs(p - np.array([8.0, 8.0, 4.0])) - np.array([7.0, 7.0, 3.0])
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    pillar = np.linalg.norm(p[..., :2] - np.array([10.0, 6.0]), axis=-1) - 1.0  # a column floor to ceiling
    d = np.minimum(-box, pillar)
    return build_gmdag(
        (d / VOXEL).astype(np.float32),
        origin=(0.0, 0.0, 0.0),
        voxel_size=VOXEL,
        bounds=((1.0, 1.0, 1.0), (15.0, 15.0, 7.0)),
    )


def rollout(
    device: str,
    steps: int,
    obstacles: int = 0,
    squad: int = 0,
    obs_buffers: int = 1,
    eager: bool = False,
) -> list[torch.Tensor]:
    cfg = EnvConfig(
        obs_buffers=obs_buffers,
        obstacles=ObstacleConfig(count=obstacles, speed_max=8.0, squad=squad),
        azimuth_bins=64,
        elevation_bins=16,
        max_steps_per_episode=12,
        sensor=SensorConfig(range_noise_std=0.01, dropout=0.01),
    )
    spawns = [
        torch.tensor(
            [[4.0, 4.0, 3.0], [12.0, 12.0, 5.0], [6.0, 11.0, 2.0], [4.0, 12.0, 4.0], [13.0, 3.0, 3.0]]
        )
    ]
    env = SdfDagEnv(load_corpus([room()], device), 16, device, cfg, spawns=spawns, eager=eager)
    g = torch.Generator().manual_seed(0)
    frames = [env.reset(seed=4).to("cpu", copy=True)]
    for _ in range(steps):
        out = env.step((torch.rand(16, 4, generator=g) * 2 - 1).to(device))
        keep = [
            out.obs,
            out.reward,
            out.info["position"],
            out.truncated.float(),
            out.info["collision"].float(),
        ]
        if env.prims is not None:
            keep.append(env.prims)
        frames += [t.to("cpu", copy=True) for t in keep]  # the env reuses its buffers
    return frames


@needs_cuda
@pytest.mark.parametrize(("obstacles", "squad"), [(0, 0), (8, 0), (4, 4)])
def test_cpu_and_cuda_rollouts_agree(obstacles: int, squad: int) -> None:
    """With moving obstacles and squads too: the same placements, motions, sweeps and traces on both, to
    the texture unit's precision: CUDA reads the static field through 8-bit filter weights (a small
    fraction of a voxel, docs/SDFDAG_RUNTIME.md), so a few rays, rewards and obstacle bounces differ a
    little while positions, truncations and collisions stay the same."""
    cpu = rollout("cpu", 30, obstacles=obstacles, squad=squad)
    cuda = rollout("cuda", 30, obstacles=obstacles, squad=squad)
    per_step = 6 if obstacles else 5  # obs, reward, position, truncated, collision (, primitives)
    assert len(cpu) == len(cuda) == 1 + 30 * per_step
    for i, (a, b) in enumerate(zip(cpu, cuda, strict=True)):
        kind = 0 if i == 0 else (i - 1) % per_step
        close = torch.isclose(a, b, atol=2e-3, rtol=1e-3)
        if kind == 0:  # observations: a grazing ray may decide its hit a step apart
            assert float(close.float().mean()) >= 0.999 and float((a - b).abs().mean()) <= 2e-4
        elif kind == 1:  # rewards: an actor's event (a new cell, a near miss) may come a step apart
            assert int((~torch.isclose(a, b, atol=1e-2)).sum()) <= 2, float((a - b).abs().max())
        elif kind == 2:  # positions, meters
            assert bool(close.all()), float((a - b).abs().max())
        elif kind in (3, 4):  # truncations, collisions
            assert torch.equal(a, b)
        else:  # primitive records: a bounce may come a step apart
            assert float(close.float().mean()) >= 0.99


@needs_cuda
@pytest.mark.parametrize(("obstacles", "squad"), [(0, 0), (8, 0), (4, 4)])
def test_the_cuda_path_is_bit_identical_to_the_eager_twin(obstacles: int, squad: int) -> None:
    """The CUDA path (the physics, episode and reward stages, the obstacles' steps and the observation
    compiled by inductor, the step replayed as a CUDA graph) against `eager=True` (plain PyTorch kernels,
    step after step). Without obstacles: bit for bit (no contraction, same rounding). With them, the
    compiled obstacle passes sum in another order (float32 reassociation, ~1e-7 m): truncations and
    collisions stay equal, every value stays within 1e-3 of the twin's."""
    fast = rollout("cuda", 20, obstacles=obstacles, squad=squad)
    eager = rollout("cuda", 20, obstacles=obstacles, squad=squad, eager=True)
    per_step = 6 if obstacles else 5  # obs, reward, position, truncated, collision (, primitives)
    assert len(fast) == len(eager) == 1 + 20 * per_step
    for i, (a, b) in enumerate(zip(fast, eager, strict=True)):
        kind = 0 if i == 0 else (i - 1) % per_step
        if obstacles == 0 or kind in (3, 4):
            assert torch.equal(a, b), i
        else:
            assert float((a - b).abs().max()) < 1e-3, i


@needs_cuda
def test_two_observation_buffers_with_two_graphs_change_no_value() -> None:
    """obs_buffers=2 records one CUDA graph per buffer: the rollout is bit-identical to one buffer's."""
    two = rollout("cuda", 20, obs_buffers=2, obstacles=4)
    one = rollout("cuda", 20, obs_buffers=1, obstacles=4)
    assert all(torch.equal(a, b) for a, b in zip(two, one, strict=True))


@needs_cuda
@pytest.mark.parametrize(("obstacles", "squad"), [(0, 0), (4, 2)])
def test_cuda_step_does_not_synchronise(
    obstacles: int, squad: int, returns_before_the_gpu: Callable[[Callable[[], object]], None]
) -> None:
    """Stepping never waits for the GPU: no synchronising torch op (sync debug mode raises on one) and
    none inside the tracer's extension (three steps queued behind a GPU sleep return before it ends)."""
    env = SdfDagEnv(
        load_corpus([room()], "cuda"),
        64,
        "cuda",
        EnvConfig(azimuth_bins=64, elevation_bins=16, obstacles=ObstacleConfig(count=obstacles, squad=squad)),
        spawns=[torch.tensor([[4.0, 4.0, 3.0], [12.0, 12.0, 5.0]])],
    )
    env.reset(seed=0)
    actions = torch.zeros(64, 4, device="cuda")
    for _ in range(3):  # two eager steps, then the step's CUDA graph is recorded (a one-time sync)
        env.step(actions)
    assert env._graphs[0] is not None  # what follows replays the recorded step
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        returns_before_the_gpu(lambda: [env.step(actions) for _ in range(3)])
    finally:
        torch.cuda.set_sync_debug_mode("default")
    out = env.step(actions)
    assert bool(torch.isfinite(out.obs).all()) and bool((out.obs > 0).any())  # the steps ran and saw walls


@needs_cuda
def test_fused_observation_is_bit_identical_on_cuda() -> None:
    """observe against observe_ref at the default resolution over three frames (fresh actors, rays on
    the band edges, a sensed frame different from the traced one): every value identical."""
    n, az, el, horizon = 96, 256, 48, 100.0
    rc = EnvConfig().reward
    g = torch.Generator(device="cuda").manual_seed(0)

    def frame() -> tuple[torch.Tensor, torch.Tensor]:
        depth = torch.rand(n, az * el, generator=g, device="cuda") * 30.0  # (N, R)
        edges = torch.tensor([rc.near_distance, rc.mid_range_min, rc.mid_range_max], device="cuda")
        pick = torch.randint(0, 8, (n, az * el), generator=g, device="cuda")  # (N, R)
        depth = torch.where(pick < 3, edges[pick.clamp(max=2)], depth)
        sem = torch.randint(1, 256, (n, az * el), generator=g, device="cuda", dtype=torch.uint8)
        miss = torch.rand(n, az * el, generator=g, device="cuda") < 0.3  # (N, R) bool
        return torch.where(miss, horizon, depth), sem.masked_fill(miss, 0)

    table = semantic_table("cuda")
    fast = torch.rand(n, 3, az, el, generator=g, device="cuda")
    ref = fast.clone()
    for step in range(3):
        fresh = torch.rand(n, generator=g, device="cuda") < 0.3  # (N,) bool
        depth, sem = frame()
        sensed, sensed_sem = (depth, sem) if step < 2 else frame()
        a = observe(fast, sensed, sensed_sem, fresh, depth, sem, table, horizon, rc)
        b = observe_ref(ref, sensed, sensed_sem, fresh, depth, sem, horizon, rc)
        assert torch.equal(fast, ref), [float((fast[:, c] - ref[:, c]).abs().max()) for c in range(3)]
        for name in ("void", "near", "mid", "front_mid", "clearance"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
