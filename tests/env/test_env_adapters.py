"""Dataset adapters reproduce the canonical DistanceMatrix layout from other sources."""

from __future__ import annotations

import math

import torch

from navi_env.config import SensorConfig
from navi_env.rays import ray_pattern
from navi_env.sim.adapters import from_contract, from_equirect_depth, from_point_cloud, resample, to_contract


def test_point_cloud_of_the_ray_pattern_is_the_depth_map() -> None:
    az, el = 32, 8
    dirs = ray_pattern(az, el, SensorConfig())  # (R, 3)
    ranges = torch.linspace(1.0, 50.0, az * el)  # (R,)
    ranges[5] = 200.0  # beyond the horizon: a miss
    pts = (dirs * ranges[:, None])[None]  # (1, R, 3)
    obs = from_point_cloud(
        pts, torch.ones(1, az * el, dtype=torch.bool), 100.0, az, el, class_id=torch.full((1, az * el), 7)
    )
    want = (ranges.clamp(max=100.0) / 100.0).view(az, el)
    assert torch.allclose(obs[0, 0], want, atol=1e-5)
    assert float(obs[0, 1].view(-1)[5]) == 0.0 and math.isclose(
        float(obs[0, 1, 0, 0]), 0.5 + 0.5 * 7 / 255, rel_tol=1e-6
    )
    assert torch.all(obs[0, 2] == 0.0)


def test_point_cloud_bin_keeps_the_nearest_point() -> None:
    pts = torch.tensor([[[5.0, 0.0, 0.1], [3.0, 0.0, 0.1], [0.0, 4.0, 0.1]]])  # two ahead, one to the left
    obs = from_point_cloud(pts, torch.ones(1, 3, dtype=torch.bool), 100.0, 8, 4)
    assert math.isclose(float(obs[0, 0, 0, 2]) * 100.0, math.hypot(3.0, 0.1), rel_tol=1e-5)
    assert math.isclose(
        float(obs[0, 0, 2, 2]) * 100.0, math.hypot(4.0, 0.1), rel_tol=1e-5
    )  # bin Az/4 is left
    assert int((obs[0, 0] < 1.0).sum()) == 2


def test_equirect_panorama_orientation() -> None:
    h, w = 90, 360
    pano = torch.full((1, h, w), 50.0)
    pano[0, :, 175:185] = 2.0  # a wall straight ahead (image centre)
    pano[0, :, 80:100] = 4.0  # a wall on the viewer's left (90 degrees left of the centre)
    pano[0, 0:10] = float("inf")  # the sky above 70 degrees: misses
    obs = from_equirect_depth(pano, 100.0, 16, 8)
    assert math.isclose(float(obs[0, 0, 0, 4]), 0.02, rel_tol=1e-6)
    assert math.isclose(float(obs[0, 0, 4, 4]), 0.04, rel_tol=1e-6)  # azimuth bin Az/4 = left
    assert math.isclose(float(obs[0, 0, 12, 4]), 0.5, rel_tol=1e-6)
    assert float(obs[0, 1, 0, 7]) == 0.0 and float(obs[0, 0, 0, 7]) == 1.0  # top bin: miss
    again = from_equirect_depth(pano * 0.5, 100.0, 16, 8, previous=obs)
    assert math.isclose(float(again[0, 2, 0, 4]), -0.01, rel_tol=1e-5)


def test_resample_keeps_bin_zero_ahead_and_round_trips() -> None:
    obs = torch.rand(2, 3, 512, 96)
    down = resample(obs, 256, 48)
    assert down.shape == (2, 3, 256, 48)
    assert torch.equal(down[:, :, 0], obs[:, :, 0, 1::2])
    assert torch.equal(resample(obs, 512, 96), obs)


def test_contract_round_trip() -> None:
    obs = torch.rand(3, 3, 16, 8)
    msg = to_contract(obs, torch.arange(3), step_id=4, timestamp=1.5)
    assert msg.depth.shape == (3, 16, 8)
    assert torch.equal(from_contract(msg), obs)
