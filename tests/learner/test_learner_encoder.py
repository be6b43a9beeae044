"""RayViTEncoder: shapes at the canonical 256×48, and fixed spherical positional encodings."""

from __future__ import annotations

import pytest
import torch

from navi_learner.config import EngineConfig
from navi_learner.encoder import RayViTEncoder, spherical_positions


def test_canonical_shapes() -> None:
    enc = RayViTEncoder((3, 256, 48), EngineConfig())
    assert enc.n_tokens == 192
    out = enc(torch.rand(2, 3, 256, 48))
    assert out.shape == (2, 128) and out.dtype == torch.float32


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
