"""RayViTEncoder: shapes at the canonical 256×48, fixed spherical positional encodings, the written-out
attention against F.scaled_dot_product_attention, and the view range (`cap_view`) against the env's own
observation writer."""

from __future__ import annotations

from dataclasses import asdict, replace

import pytest
import torch
import torch.nn.functional as F

from navi_env.sim.observation import write_observation
from navi_learner.config import TASK_VIEW_RANGE, EngineConfig, TrainConfig, engine_overrides, resolve
from navi_learner.engine.encoder import RayViTEncoder, attention_explicit, spherical_positions
from navi_learner.engine.tokens import cap_view, patchify


def test_canonical_shapes() -> None:
    enc = RayViTEncoder((3, 256, 48), EngineConfig())
    assert enc.patch == (16, 16) and enc.n_tokens == 48  # 16 azimuth × 3 elevation patches
    assert enc.embed.in_features == 4 * 16 * 16  # the three channels and near_field
    out = enc(torch.rand(2, 3, 256, 48))
    assert out.shape == (2, 128) and out.dtype == torch.float32


def test_square_patch_of_older_checkpoints() -> None:
    """An engine dict written before patch_el existed (square patches of patch_size) rebuilds them."""
    for side, tokens in ((8, 192), (4, 768)):
        old = {k: v for k, v in asdict(EngineConfig(patch_size=side)).items() if k != "patch_el"}
        enc = RayViTEncoder((3, 256, 48), EngineConfig.from_dict(old))
        assert enc.patch == (side, side) and enc.n_tokens == tokens
        assert TrainConfig.from_dict(asdict(TrainConfig()) | {"engine": old}).engine.patch == (side, side)
    assert EngineConfig.from_dict(asdict(EngineConfig())) == EngineConfig()  # today's dicts round-trip


def test_patchify_puts_each_ray_in_its_patch() -> None:
    """Token t = (azimuth patch i, elevation patch j) at t = i·Pe + j holds exactly the rays of its
    pa × pe block, features in (channel, azimuth, elevation) order."""
    c, az, el, pa, pe = 2, 16, 8, 4, 2
    a = torch.arange(az).view(1, az, 1).expand(c, az, el)  # (C, Az, El) azimuth index
    e = torch.arange(el).view(1, 1, el).expand(c, az, el)  # (C, Az, El) elevation index
    ch = torch.arange(c).view(c, 1, 1).expand(c, az, el)  # (C, Az, El) channel index
    obs = (ch * 10_000 + a * 100 + e).float().unsqueeze(0)  # (1, C, Az, El) ray codes
    tokens = patchify(obs, (pa, pe))  # (1, P, C·pa·pe)
    pe_n = el // pe
    assert tokens.shape == (1, (az // pa) * pe_n, c * pa * pe)
    for t in range(tokens.shape[1]):
        i, j = divmod(t, pe_n)
        want = [
            k * 10_000 + (i * pa + x) * 100 + (j * pe + y)
            for k in range(c)
            for x in range(pa)
            for y in range(pe)
        ]
        assert tokens[0, t].long().tolist() == want
    assert torch.equal(patchify(obs, 4), patchify(obs, (4, 4)))  # an int is a square patch


def test_positional_encoding_is_fixed() -> None:
    cfg = EngineConfig(embed_dim=32, patch_size=4, encoder_layers=1, encoder_heads=2)
    enc = RayViTEncoder((3, 16, 8), cfg)
    assert "pos" not in dict(enc.named_parameters()) and "pos" not in enc.state_dict()
    pos0 = enc.pos.clone()
    assert torch.equal(pos0, RayViTEncoder((3, 16, 8), cfg).pos)  # same for every instance and seed
    opt = torch.optim.SGD(enc.parameters(), lr=1.0)
    enc(torch.rand(4, 3, 16, 8)).pow(2).sum().backward()
    opt.step()
    assert torch.equal(enc.pos, pos0)


def test_positions_are_distinct_and_periodic_in_azimuth() -> None:
    pos = spherical_positions(32, 6, 128)  # (192, 128)
    assert pos.shape == (192, 128)
    assert torch.unique(pos, dim=0).shape[0] == 192
    unit = pos[:, :3]  # direction vectors
    assert torch.allclose(unit.norm(dim=1), torch.ones(192), atol=1e-6)
    # azimuth-major order: the first and last azimuth patches are neighbours across 360°
    first, last = unit[0], unit[31 * 6]
    assert torch.dot(first, last) > 0.9


def test_patch_divisibility_is_checked() -> None:
    with pytest.raises(ValueError, match="divisible"):
        RayViTEncoder((3, 20, 8), EngineConfig())
    with pytest.raises(ValueError, match="divisible"):
        RayViTEncoder((3, 256, 44), EngineConfig())  # 44 elevation bins: not a multiple of 16


def test_a_patch_longer_than_the_view_is_capped_at_it() -> None:
    """The toy env's 16 × 8 view under the default 16 × 16 patch is one 16 × 8 patch."""
    enc = RayViTEncoder((3, 16, 8), EngineConfig())
    assert enc.patch == (16, 8) and enc.n_tokens == 1
    assert EngineConfig(patch_size=32, patch_el=4).patch_for(16, 8) == (16, 4)
    with pytest.raises(ValueError, match="divisible"):
        EngineConfig(patch_size=16, patch_el=16).patch_for(24, 8)  # 24 rays: capped at 16, not a divisor


def test_explicit_attention_is_the_same_function_as_sdpa() -> None:
    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(5, 4, 48, 32, generator=g) for _ in "qkv")  # (N, h, P, d)
    ref = F.scaled_dot_product_attention(q, k, v)  # (N, h, P, d)
    assert torch.allclose(attention_explicit(q, k, v), ref, atol=1e-5, rtol=0)
    half = attention_explicit(*(t.bfloat16() for t in (q, k, v)))  # the softmax stays float32
    assert half.dtype == torch.bfloat16 and torch.allclose(half.float(), ref, atol=0.05, rtol=0)


@pytest.mark.parametrize("attention", ["explicit", "fused"])
def test_encoder_attention_option_matches_sdpa_in_value_and_gradient(attention: str) -> None:
    """The option changes how attention is computed, not the function: the same weights give the same
    embedding and the same gradients, and a checkpoint loads into either (fused here runs its CPU twin
    through the registered operator and its autograd)."""
    torch.manual_seed(0)
    shape = (3, 32, 8)
    fused = RayViTEncoder(shape, EngineConfig.tiny())
    written = RayViTEncoder(shape, EngineConfig.tiny(attention=attention))  # type: ignore[arg-type]
    written.load_state_dict(fused.state_dict())
    obs = torch.rand(6, *shape)  # (N, 3, Az, El)
    outs, grads = [], []
    for enc in (fused, written):
        y = enc(obs)  # (N, D)
        y.square().sum().backward()
        outs.append(y.detach())
        grads.append(torch.cat([p.grad.flatten() for p in enc.parameters()]))  # type: ignore[union-attr]
    assert torch.allclose(outs[0], outs[1], atol=1e-5, rtol=0)
    assert torch.allclose(grads[0], grads[1], atol=1e-4, rtol=1e-4)


def test_auto_attention_is_sdpa_on_a_cpu_and_where_the_fused_kernel_cannot_serve() -> None:
    """auto (the default) computes SDPA's very numbers on a CPU (the fused operator is for CUDA), and an
    encoder the fused kernel cannot take (heads 12 wide, or more than 128 tokens) gets SDPA on every
    device; `fused` asked for by name refuses such an encoder."""
    torch.manual_seed(0)
    shape = (3, 32, 8)
    assert EngineConfig().attention == "auto"
    auto = RayViTEncoder(shape, EngineConfig.tiny())
    sdpa = RayViTEncoder(shape, EngineConfig.tiny(attention="sdpa"))
    sdpa.load_state_dict(auto.state_dict())
    obs = torch.rand(4, *shape)  # (N, 3, Az, El)
    assert auto.attention == "auto" and all(b.fused_on_cuda and not b.fused for b in auto.blocks)
    assert torch.equal(auto(obs), sdpa(obs))
    wide = EngineConfig.tiny(embed_dim=24, encoder_heads=2)  # heads 12 wide
    many = EngineConfig.tiny(patch_size=2, patch_el=2)  # 16 x 4 = 64 tokens of 3 x 32 x 8: fits
    assert RayViTEncoder(shape, wide).attention == "sdpa" and RayViTEncoder(shape, many).attention == "auto"
    assert (
        RayViTEncoder((3, 64, 16), EngineConfig.tiny(patch_size=2, patch_el=2)).attention == "sdpa"
    )  # 256 tokens
    with pytest.raises(ValueError, match="12 wide"):
        RayViTEncoder(shape, replace(wide, attention="fused"))


def test_engine_option_parses_the_attention_and_refuses_others() -> None:
    assert engine_overrides(["attention=explicit"]) == {"attention": "explicit"}
    with pytest.raises(ValueError, match="sdpa, explicit"):
        engine_overrides(["attention=flash"])
    with pytest.raises(ValueError, match="sdpa or explicit"):
        RayViTEncoder((3, 32, 8), EngineConfig.tiny(attention="flash"))


def _frames(depth0: torch.Tensor, depth1: torch.Tensor, semantic: torch.Tensor) -> torch.Tensor:
    """The env's observation (N, 3, Az, El) of depth1 (N, Az, El) meters one step after depth0, both with
    semantic (N, Az, El) uint8 (0: a miss, whose depth is the 100 m horizon), written by the env's own
    write_observation."""
    n, az, el = depth1.shape
    obs = torch.zeros(n, 3, az, el)  # (N, 3, Az, El)
    fresh = torch.zeros(n, dtype=torch.bool)  # (N,)
    for depth in (depth0, depth1):
        flat = depth.reshape(n, -1)  # (N, R)
        write_observation(obs, flat, semantic.reshape(n, -1), semantic.reshape(n, -1) > 0, fresh, 100.0)
    return obs


def test_a_capped_view_is_the_view_of_a_world_that_ends_at_the_view_range() -> None:
    """cap_view of the env's observation equals the observation the env writes where every ray beyond
    the view range (misses included) hits an unknown-class surface (code 1) at it: depth, semantic and
    delta depth, both frames capped."""
    g = torch.Generator().manual_seed(0)
    n, az, el, view_m = 4, 16, 8, 20.0
    far_or_near = torch.rand(2, n, az, el, generator=g) < 0.5  # (2, N, Az, El) bool
    near = torch.rand(2, n, az, el, generator=g) * 19.0 + 0.2  # (2, N, Az, El) meters in [0.2, 19.2)
    far = torch.rand(2, n, az, el, generator=g) * 79.0 + 21.0  # (2, N, Az, El) meters in [21, 100)
    depth = torch.where(far_or_near, far, near)  # (2, N, Az, El)
    semantic = torch.randint(1, 200, (n, az, el), generator=g, dtype=torch.uint8)  # (N, Az, El)
    missed = torch.rand(n, az, el, generator=g) < 0.2  # (N, Az, El) bool
    semantic[missed] = 0
    depth[1][missed] = 100.0
    fraction = float(torch.tensor(view_m / 100.0, dtype=torch.float16))  # as the encoder rounds it
    capped = cap_view(_frames(depth[0], depth[1], semantic), fraction)  # (N, 3, Az, El)
    view = fraction * 100.0  # meters
    beyond = depth[1] > view_m  # (N, Az, El) bool
    ends = torch.where(beyond, torch.ones_like(semantic), semantic)  # (N, Az, El) code 1: class 0
    expected = _frames(depth[0].clamp(max=view), depth[1].clamp(max=view), ends)  # (N, 3, Az, El)
    assert torch.equal(capped, expected)
    assert beyond.any() and (~beyond).any() and (depth[0] > view_m).ne(beyond).any()


def test_a_capped_view_keeps_the_goal_mark_and_the_near_field() -> None:
    """Four rays: near (it came from beyond), a far hit, a miss, a far ray with the goal mark."""
    obs = torch.tensor(
        [[0.125, 0.5, 1.0, 0.875], [0.75, 0.625, 0.0, -0.25], [-0.5, 0.125, 0.0, 0.25]]
    )  # (C, R)
    out = cap_view(obs.view(1, 3, 1, 4), 0.25).view(3, 4)  # (C, R)
    assert out[0].tolist() == [0.125, 0.25, 0.25, 0.25]  # depth capped at the view range
    assert out[1].tolist() == [0.75, 0.5, 0.5, -0.25]  # far hits and misses unknown; the mark stays
    assert out[2].tolist() == [-0.125, 0.0, 0.0, 0.0]  # from 0.625 (capped 0.25) to 0.125; the rest far
    assert torch.equal(cap_view(obs.view(1, 3, 1, 4), 1.0), obs.view(1, 3, 1, 4))


def test_an_encoder_with_a_view_range_does_not_see_beyond_it() -> None:
    """With view_range 0.2 the embedding is the same whatever lies beyond 20 m; without, it is not."""
    g = torch.Generator().manual_seed(0)
    left = torch.arange(16).view(1, 16, 1) < 4  # (1, Az, El) the left quarter of a 16 x 8 view
    near = torch.rand(2, 2, 16, 8, generator=g) * 10.0 + 0.5  # (2, N, Az, El) meters: two frames
    views = []
    for _ in range(2):  # two worlds that differ only beyond 20 m, in the left quarter
        far = torch.rand(2, 2, 16, 8, generator=g) * 70.0 + 25.0  # (2, N, Az, El) meters
        depth = torch.where(left, far, near)  # (2, N, Az, El)
        classes = torch.randint(0, 9, (2, 16, 8), generator=g, dtype=torch.uint8)  # (N, Az, El), 0 a miss
        semantic = torch.where(left, classes, torch.full_like(classes, 7))  # (N, Az, El)
        depth[1] = torch.where(semantic == 0, 100.0, depth[1])
        views.append(_frames(depth[0], depth[1], semantic))  # (N, 3, Az, El)
    capped, whole = (RayViTEncoder((3, 16, 8), EngineConfig.tiny(view_range=v)) for v in (0.2, 1.0))
    whole.load_state_dict(capped.state_dict())  # the same weights
    with torch.no_grad():
        assert torch.equal(capped(views[0]), capped(views[1]))
        assert not torch.allclose(whole(views[0]), whole(views[1]))


def test_the_view_range_is_a_fraction_of_the_horizon_fixed_per_task_when_a_run_starts() -> None:
    assert engine_overrides(["view_range=0.2"]) == {"view_range": 0.2}
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="view_range must lie in"):
            EngineConfig(view_range=bad)
    for task, view in (("explore", 1.0), ("pointgoal", 0.2)):  # 0, the default: the task's
        assert resolve(TrainConfig(task=task, device="cpu"), (3, 256, 48)).engine.view_range == view
        assert TASK_VIEW_RANGE[task] == view
    chosen = TrainConfig(task="pointgoal", device="cpu", engine=EngineConfig(view_range=1.0))
    assert resolve(chosen, (3, 256, 48)).engine.view_range == 1.0  # a chosen range stays
    kept = TrainConfig.from_dict(asdict(resolve(TrainConfig(task="pointgoal", device="cpu"), (3, 256, 48))))
    assert kept.engine.view_range == 0.2  # stored with every checkpoint's config
    old = {k: v for k, v in asdict(EngineConfig()).items() if k != "view_range"}
    assert EngineConfig.from_dict(old).view_range == 1.0  # older checkpoints read the whole horizon


def test_an_engine_left_at_the_task_default_outside_a_run_reads_the_whole_horizon() -> None:
    torch.manual_seed(0)
    obs = torch.rand(2, 3, 16, 8)  # (N, C, Az, El)
    unset, whole = (RayViTEncoder((3, 16, 8), EngineConfig.tiny(view_range=v)) for v in (0.0, 1.0))
    whole.load_state_dict(unset.state_dict())
    with torch.no_grad():
        assert torch.equal(unset(obs), whole(obs))
