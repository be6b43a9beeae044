"""DistanceMatrix v2 layout, the sensor pattern and model, the view statistics and dataset adapters."""

from __future__ import annotations

import math

import torch

from navi_env.config import EnvConfig, SensorConfig
from navi_env.rays import ray_pattern, spherical_directions
from navi_env.sim.observation import (
    front_bin_count,
    is_front,
    observe,
    observe_ref,
    pack,
    round_to_half,
    semantic_table,
    unpack,
    view_stats,
    write_observation,
)
from navi_env.sim.sensor import apply_sensor, dome_lidar

CFG = EnvConfig()


def test_ray_pattern_layout() -> None:
    az, el = 16, 8
    d = ray_pattern(az, el, SensorConfig()).reshape(az, el, 3)  # ray r = a * El + e
    assert torch.allclose(d.norm(dim=-1), torch.ones(az, el), atol=1e-6)
    mid = el // 2
    assert float(d[0, mid, 0]) > 0.9 and abs(float(d[0, mid, 1])) < 1e-6  # bin 0 straight ahead (+X)
    assert float(d[az // 4, mid, 1]) > 0.9  # a quarter turn is to the left (+Y)
    assert float(d[az // 2, mid, 0]) < -0.9  # half a turn is behind
    assert torch.all(d[:, 1:, 2] > d[:, :-1, 2])  # elevation from bottom to top
    assert float(d[0, 0, 2]) < -0.9 and float(d[0, -1, 2]) > 0.9  # full sphere


def test_full_sphere_pattern_is_the_tracers_pattern() -> None:
    assert torch.equal(ray_pattern(256, 48, SensorConfig()), spherical_directions(256, 48))


def test_dome_lidar_preset_limits_elevation() -> None:
    s = dome_lidar()
    d = ray_pattern(32, 8, s)
    elevation = torch.rad2deg(torch.asin(d[:, 2]))
    assert float(elevation.min()) > -7.0 and float(elevation.max()) < 52.0
    assert s.enabled


def test_write_observation_channels_and_delta() -> None:
    n, az, el = 2, 4, 2
    obs = torch.zeros(n, 3, az, el)
    depth = torch.tensor([[1.0] * 8, [100.0] * 8])
    sem = torch.tensor([[3] * 8, [0] * 8], dtype=torch.uint8)
    hit = sem > 0
    write_observation(obs, depth, sem, hit, torch.ones(n, dtype=torch.bool), 100.0)
    near = torch.tensor(0.01).half().float()  # channel 0 is depth / horizon rounded to float16
    assert torch.all(obs[0, 0] == near) and torch.all(obs[1, 0] == 1.0)
    assert abs(float(near) - 0.01) <= 0.01 * 2.0**-11
    assert math.isclose(float(obs[0, 1, 0, 0]), 0.5 + 0.5 * 2 / 255, rel_tol=1e-6) and torch.all(
        obs[1, 1] == 0.0
    )
    assert torch.all(obs[:, 2] == 0.0)  # fresh: no delta
    write_observation(obs, depth * 0.5, sem, hit, torch.tensor([False, True]), 100.0)
    closer = float(torch.tensor(0.005).half()) - float(near)  # exact: two float16 values in [0, 1]
    assert torch.all(obs[0, 2] == closer) and math.isclose(closer, -0.005, rel_tol=1e-3)  # came closer
    assert torch.all(obs[1, 2] == 0.0)


def test_view_stats_fractions_front_and_clearance() -> None:
    az, el = 8, 2
    depth = torch.full((1, az, el), 100.0)
    depth[0, 1:4] = 5.0  # mid-range structure on the left (bins 1..3: 45, 90, 135 degrees)
    depth[0, 0] = 0.5  # near field straight ahead
    depth[0, 0, 1] = 0.25  # the nearest surface
    hit = depth < 100.0
    s = view_stats(depth.reshape(1, -1), hit.reshape(1, -1), az, CFG.reward)
    assert math.isclose(float(s.void), 4 / 8, rel_tol=1e-6)
    assert math.isclose(float(s.near), 1 / 8, rel_tol=1e-6)
    assert math.isclose(float(s.mid), 3 / 8, rel_tol=1e-6)
    # the front half is bins 7, 0, 1 (cos > 0): only bin 1 holds mid-range rays
    assert math.isclose(float(s.front_mid), 1 / 3, rel_tol=1e-6)
    assert float(s.clearance) == 0.25


def test_front_half_is_where_the_cosine_is_positive() -> None:
    for az in (4, 5, 6, 7, 8, 30, 256):
        bins = torch.arange(az)
        want = torch.cos(2 * math.pi * bins.double() / az) > 1e-9
        assert torch.equal(is_front(bins, az), want)
        assert front_bin_count(az) == int(want.sum())


def test_sensor_noise_and_dropout() -> None:
    n, r = 64, 512
    depth = torch.full((n, r), 10.0)
    sem = torch.full((n, r), 3, dtype=torch.uint8)
    sem[:, :10] = 0
    depth[:, :10] = 100.0
    seed, tick = torch.tensor(0), torch.tensor(1)
    clean = apply_sensor(depth, sem, SensorConfig(), 100.0, seed, tick)
    assert torch.equal(clean[0], depth) and torch.equal(clean[1], sem)
    cfg = SensorConfig(range_noise_std=0.1, dropout=0.05)
    noisy, seen = apply_sensor(depth, sem, cfg, 100.0, seed, tick)
    kept = seen > 0
    assert abs(float(noisy[kept].std()) - 0.1) < 0.01 and abs(float(noisy[kept].mean()) - 10.0) < 0.01
    assert torch.all(noisy[:, :10] == 100.0) and torch.all(seen[:, :10] == 0)  # misses stay misses
    assert abs(float((seen[:, 10:] == 0).float().mean()) - 0.05) < 0.01
    assert torch.all(noisy[~kept] == 100.0)
    again = apply_sensor(depth, sem, cfg, 100.0, seed, tick)
    assert torch.equal(again[0], noisy) and torch.equal(again[1], seen)
    other = apply_sensor(depth, sem, cfg, 100.0, seed, torch.tensor(2))
    assert not torch.equal(other[0], noisy)


def test_dropped_rays_read_as_misses_in_the_observation() -> None:
    depth = torch.full((1, 8), 10.0)
    sem = torch.full((1, 8), 2, dtype=torch.uint8)
    d, s = apply_sensor(depth, sem, SensorConfig(dropout=0.5), 100.0, torch.tensor(3), torch.tensor(0))
    obs = torch.zeros(1, 3, 4, 2)
    write_observation(obs, d, s, s > 0, torch.ones(1, dtype=torch.bool), 100.0)
    ch0, ch1 = obs[0, 0].reshape(-1), obs[0, 1].reshape(-1)
    dropped = s[0] == 0
    assert 0 < int(dropped.sum()) < 8
    assert torch.all(ch0[dropped] == 1.0) and torch.all(ch1[dropped] == 0.0)
    assert torch.allclose(ch1[~dropped], torch.full_like(ch1[~dropped], 0.5 + 0.5 / 255))


def random_frame(n: int, az: int, el: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (N, R) float32 and semantic (N, R) uint8 with misses, hits of every class and rays exactly
    on the near and mid-range band edges."""
    g = torch.Generator().manual_seed(seed)
    r = az * el
    depth = torch.rand(n, r, generator=g) * 30.0  # (N, R) meters
    edges = torch.tensor([CFG.reward.near_distance, CFG.reward.mid_range_min, CFG.reward.mid_range_max])
    pick = torch.randint(0, 8, (n, r), generator=g)  # (N, R) int64
    depth = torch.where(pick < 3, edges[pick.clamp(max=2)], depth)
    semantic = torch.randint(1, 256, (n, r), generator=g, dtype=torch.uint8)  # (N, R) uint8
    miss = torch.rand(n, r, generator=g) < 0.3  # (N, R) bool
    return torch.where(miss, CFG.horizon, depth), semantic.masked_fill(miss, 0)


def test_fused_observation_matches_the_reference_on_cpu() -> None:
    """observe (torch.compile on CPU) against observe_ref over three frames: every channel and statistic
    bit for bit (channel 2 is the exact difference of two float16 values)."""
    n, az, el = 6, 16, 4
    table = semantic_table("cpu")
    fast = torch.rand(n, 3, az, el, generator=torch.Generator().manual_seed(9))
    ref = fast.clone()
    fresh = [
        torch.ones(n, dtype=torch.bool),
        torch.tensor([False, True] * 3),
        torch.zeros(n, dtype=torch.bool),
    ]
    for step in range(3):
        depth, sem = random_frame(n, az, el, step)
        sensed, sensed_sem = (depth, sem) if step < 2 else random_frame(n, az, el, 10)  # sensor on
        a = observe(fast, sensed, sensed_sem, fresh[step], depth, sem, table, CFG.horizon, CFG.reward)
        b = observe_ref(ref, sensed, sensed_sem, fresh[step], depth, sem, CFG.horizon, CFG.reward)
        assert torch.equal(fast, ref)
        assert torch.all(fast[fresh[step], 2] == 0.0) and bool((fast[~fresh[step], 2] != 0.0).any()) == (
            step > 0
        )
        for name in ("void", "near", "mid", "front_mid", "clearance"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert float(a.front_mid.abs().max()) > 0.0
        fast.copy_(ref)  # the next delta starts from the same previous frame


def test_fused_observation_into_the_other_buffer_matches_one_buffer() -> None:
    """observe with prev (an env that writes two buffers in turn) against observe_ref over one buffer:
    each frame written into the other buffer, with the delta read from the last one, is bit-identical."""
    n, az, el = 6, 16, 4
    table = semantic_table("cpu")
    ref = torch.rand(n, 3, az, el, generator=torch.Generator().manual_seed(9))
    ring = (ref.clone(), torch.zeros_like(ref))  # the frame before the first is in ring[0]
    fresh = torch.tensor([True, False] * 3)
    for step in range(4):
        depth, sem = random_frame(n, az, el, step)
        out, prev = ring[(step + 1) % 2], ring[step % 2]
        a = observe(out, depth, sem, fresh, depth, sem, table, CFG.horizon, CFG.reward, prev)
        b = observe_ref(ref, depth, sem, fresh, depth, sem, CFG.horizon, CFG.reward)
        assert torch.equal(out, ref) and bool((out[~fresh, 2] != 0.0).any())
        for name in ("void", "near", "mid", "front_mid", "clearance"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_semantic_table_is_channel_one() -> None:
    codes = torch.arange(256, dtype=torch.uint8)[None]  # (1, 256)
    obs = torch.zeros(1, 3, 64, 4)
    write_observation(obs, torch.zeros(1, 256), codes, codes > 0, torch.ones(1, dtype=torch.bool), 100.0)
    assert torch.equal(semantic_table("cpu"), obs[0, 1].reshape(-1))
    assert float(semantic_table("cpu")[0]) == 0.0 and float(semantic_table("cpu")[1]) == 0.5


def test_compact_form_gives_back_every_channel_bit_for_bit() -> None:
    """pack then unpack over four frames written by observe_ref (fresh actors, the sensor on, every
    class, misses) equals the float32 observations; channel 0 is depth / horizon within float16
    rounding; without the reset flags the deltas of fresh frames come out wrong."""
    n, az, el, t_len = 5, 16, 4, 4
    table = semantic_table("cpu")
    obs = torch.zeros(n, 3, az, el)
    depth16 = torch.zeros(t_len + 1, n, az, el, dtype=torch.float16)  # (T+1, N, Az, El)
    semantic = torch.zeros(t_len, n, az, el, dtype=torch.uint8)  # (T, N, Az, El)
    fresh = torch.rand(t_len, n, generator=torch.Generator().manual_seed(4)) < 0.3  # (T, N)
    fresh[0] = True
    frames = []
    for t in range(t_len):
        depth, sem = random_frame(n, az, el, 20 + t)
        observe_ref(obs, depth, sem, fresh[t], depth, sem, CFG.horizon, CFG.reward)
        err = (obs[:, 0].reshape(n, -1) - depth / CFG.horizon).abs()  # (N, R)
        assert torch.all(err <= (depth / CFG.horizon) * 2.0**-11)
        frames.append(obs.clone())
        pack(obs, depth16[t + 1], semantic[t])
    back = unpack(depth16, semantic, fresh, table)  # (T, N, 3, Az, El)
    assert torch.equal(back, torch.stack(frames))
    assert bool((back[1:, :, 2] != 0).any()) and torch.all(back[fresh][:, 2] == 0)
    # the reset flags matter: without them a fresh frame's delta is taken across two episodes
    assert not torch.equal(unpack(depth16, semantic, torch.zeros_like(fresh), table), back)
    # compiled (the minibatch decode compiles it): the same bits (aot_eager: the traced graph run by eager
    # kernels)
    traced = torch.compile(unpack, backend="aot_eager", fullgraph=True, dynamic=False)
    assert torch.equal(traced(depth16, semantic, fresh, table), back)


def test_round_to_half_is_the_float16_rounding() -> None:
    """Every finite float16 value, every midpoint between two neighbours (ties go to even) and the float32
    values either side of it, and random values of both signs, in the normal and subnormal ranges."""
    h = torch.arange(0, 0x7C00, dtype=torch.int32).to(torch.int16).view(torch.float16).float()  # (31744,)
    mids = ((h[:-1].double() + h[1:].double()) / 2).float()  # exact in float32
    g = torch.Generator().manual_seed(0)
    values = torch.cat(
        [
            h,
            mids,
            torch.nextafter(mids, torch.zeros(())),
            torch.nextafter(mids, torch.full((), 1e9)),
            torch.rand(10**6, generator=g) * 2.0,
            torch.rand(10**5, generator=g) * 2.0**-13,
        ]
    )
    values = torch.cat([values, -values])
    assert torch.equal(round_to_half(values), values.half().float())
