"""Checkpoint v3: round trip, weights_only loading, version check, crash-safe writes, pruning."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from navi_learner.config import EngineConfig, TrainConfig
from navi_learner.engine.policy import CognitiveMambaPolicy
from navi_learner.serving import checkpoint as ck
from navi_learner.serving.checkpoint import CheckpointError, CheckpointMeta, load_checkpoint, save_checkpoint

ENGINE = EngineConfig(
    embed_dim=16,
    patch_size=4,
    encoder_layers=1,
    encoder_heads=2,
    ssm_head_dim=8,
    head_hidden=16,
    rnd_dim=8,
    memory_slots=4,
)


def meta(step: int) -> CheckpointMeta:
    cfg = TrainConfig(engine=ENGINE)
    return CheckpointMeta(
        step_id=step,
        episode_count=7,
        reward_ema=0.25,
        wall_time_hours=0.5,
        temporal_core="mamba2",
        run_id="run-x",
        config=cfg.to_dict(),
        obs_shape=[3, 8, 8],
        parent_checkpoint=None,
        corpus_summary={"kind": "toy", "scenes": 1},
    )


def policy_and_optimizer() -> tuple[CognitiveMambaPolicy, torch.optim.Adam]:
    policy = CognitiveMambaPolicy((3, 8, 8), ENGINE)
    opt = torch.optim.Adam([p for p in policy.parameters() if p.requires_grad], lr=1e-3)
    policy.heads.log_std.sum().backward()
    opt.step()
    return policy, opt


def test_round_trip_restores_weights_optimizer_and_metadata(tmp_path: Path) -> None:
    policy, opt = policy_and_optimizer()
    path = save_checkpoint(tmp_path / "a.pt", policy.state_dict(), opt.state_dict(), meta(1234))
    loaded = load_checkpoint(path)
    fresh = CognitiveMambaPolicy((3, 8, 8), ENGINE)
    fresh.load_state_dict(loaded.model)
    for k, v in policy.state_dict().items():
        assert torch.equal(v, fresh.state_dict()[k]), k
    opt2 = torch.optim.Adam([p for p in fresh.parameters() if p.requires_grad], lr=1e-3)
    assert loaded.optimizer is not None
    opt2.load_state_dict(loaded.optimizer)
    want, got = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert want and want.keys() == got.keys()
    for idx in want:
        assert torch.equal(want[idx]["exp_avg"], got[idx]["exp_avg"])
    m = loaded.meta
    assert (m.step_id, m.episode_count, m.reward_ema, m.temporal_core, m.run_id) == (
        1234,
        7,
        0.25,
        "mamba2",
        "run-x",
    )
    assert m.created_at and m.code_version.startswith("navi-learner")
    assert TrainConfig.from_dict(m.config).engine == ENGINE


def test_file_loads_with_plain_weights_only_torch_load(tmp_path: Path) -> None:
    policy, opt = policy_and_optimizer()
    path = save_checkpoint(tmp_path / "a.pt", policy.state_dict(), opt.state_dict(), meta(1))
    raw = torch.load(path, weights_only=True)
    assert raw["format_version"] == 3
    assert set(raw) == {"format_version", "model", "optimizer", "meta"}


def test_other_versions_fail_fast(tmp_path: Path) -> None:
    torch.save({"format_version": 2, "model": {}}, tmp_path / "v2.pt")
    with pytest.raises(CheckpointError, match=r"v2.*only v3"):
        load_checkpoint(tmp_path / "v2.pt")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "legacy.pt")
    with pytest.raises(CheckpointError, match="no format_version"):
        load_checkpoint(tmp_path / "legacy.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "junk.pt")


def test_crash_between_temp_write_and_replace_keeps_previous(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    policy, opt = policy_and_optimizer()
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, policy.state_dict(), opt.state_dict(), meta(100))

    def crash(src: str, dst: str) -> None:
        raise OSError("simulated power loss before rename")

    monkeypatch.setattr(ck.os, "replace", crash)
    with pytest.raises(OSError, match="simulated"):
        save_checkpoint(path, policy.state_dict(), opt.state_dict(), meta(200))
    monkeypatch.undo()
    assert load_checkpoint(path).meta.step_id == 100
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]


def test_prune_keeps_newest(tmp_path: Path) -> None:
    policy, _ = policy_and_optimizer()
    for step in (10, 20, 30, 40):
        save_checkpoint(tmp_path / ck.checkpoint_name(step), policy.state_dict(), None, meta(step))
    ck.prune_checkpoints(tmp_path, keep=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == [ck.checkpoint_name(30), ck.checkpoint_name(40)]
