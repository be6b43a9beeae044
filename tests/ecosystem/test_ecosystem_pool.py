"""The pooled view an MLP reads: every pooled ray is the nearest ray of its block (its depth, semantic and
delta depth), azimuth block 0 is centred straight ahead, the goal mark survives pooling, and the bounds
hold."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from navi_env.config import EnvConfig
from navi_env.ecosystem.batch import MLP_VIEW, make_batched_env, obs_bounds, pool_view, view_of

pytestmark = pytest.mark.usefixtures("single_thread")


def pooled_by_hand(obs: torch.Tensor, view: tuple[int, int]) -> torch.Tensor:
    """The definition, ray by ray: block (a, e) holds azimuth bins a*ka - ka//2 ... a*ka + ka - ka//2 - 1
    (modulo Az) and elevation bins e*ke ... e*ke + ke - 1; it reads the nearest ray, with the block's
    lowest semantic value where that is negative."""
    n, c, az, el = obs.shape
    ka, ke = az // view[0], el // view[1]
    out = torch.empty(n, c, *view)  # (N, 3, Az', El')
    for i in range(n):
        for a in range(view[0]):
            for e in range(view[1]):
                rays = [((a * ka + d - ka // 2) % az, e * ke + k) for d in range(ka) for k in range(ke)]
                depths = torch.stack([obs[i, 0, x, y] for x, y in rays])  # (K,)
                x, y = rays[int(depths.argmin())]
                out[i, :, a, e] = obs[i, :, x, y]
                mark = min(float(obs[i, 1, x2, y2]) for x2, y2 in rays)
                if mark < 0:
                    out[i, 1, a, e] = mark
    return out


@pytest.mark.parametrize(("shape", "view"), [((3, 3, 16, 8), (4, 2)), ((2, 3, 12, 6), (3, 3))])
def test_pool_view_keeps_the_nearest_ray_of_every_block(
    shape: tuple[int, ...], view: tuple[int, int]
) -> None:
    gen = torch.Generator().manual_seed(1)
    obs = torch.rand(shape, generator=gen)  # (N, 3, Az, El)
    obs[:, 1] = torch.where(torch.rand(shape[0], shape[2], shape[3], generator=gen) < 0.1, -0.5, obs[:, 1])
    pooled = pool_view(obs, view)
    assert pooled.shape == (shape[0], 3, *view)
    assert torch.equal(pooled, pooled_by_hand(obs, view))
    assert (pooled[:, 1] < 0).any()  # some goal marks were pooled


def test_pooled_full_view_sees_every_wall_of_the_traced_small_view_or_nearer(corpus: Path) -> None:
    """On a scene, each pooled ray is at most as far as the ray of a 16 x 4 pattern traced from the same
    spawn (a 48 x 12 pattern holds every 16 x 4 ray, the middle one of each 3 x 3 block), somewhere nearer,
    a surface straight ahead shows in pooled bin 0, and the bounds of the pooled space hold."""
    full = make_batched_env(corpus, 6, "cpu", EnvConfig(azimuth_bins=48, elevation_bins=12))
    small = make_batched_env(corpus, 6, "cpu", EnvConfig(azimuth_bins=16, elevation_bins=4))
    pooled = pool_view(full.reset(seed=4), MLP_VIEW)  # (6, 3, 16, 4)
    traced = small.reset(seed=4)  # (6, 3, 16, 4) the same spawns
    assert (pooled[:, 0] <= traced[:, 0]).all() and (pooled[:, 0] < traced[:, 0]).any()
    low, high = obs_bounds(full, MLP_VIEW)  # (3, 16, 4) each
    assert ((pooled >= low) & (pooled <= high)).all()
    ahead = full.obs.clone()  # (6, 3, 48, 12)
    ahead[:, 0, 0, :] = 0.001  # a surface 10 cm straight ahead, in fine bin 0 only
    assert torch.all(pool_view(ahead, MLP_VIEW)[:, 0, 0, :] == 0.001)
    assert torch.all(pool_view(ahead, MLP_VIEW)[:, 0, 1:, :] > 0.001)


def test_view_of_passes_an_env_at_its_own_view_and_refuses_blocks_that_do_not_split(corpus: Path) -> None:
    env = make_batched_env(corpus, 2, "cpu", replace(EnvConfig(), azimuth_bins=16, elevation_bins=4))
    assert view_of(env, MLP_VIEW) is None and view_of(env, None) is None
    assert view_of(env, (8, 2)) == (8, 2)
    with pytest.raises(ValueError, match="does not pool"):
        view_of(env, (5, 2))
