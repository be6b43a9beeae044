"""Model registry: immutable versions, latest = best reward_ema, aliases, rollback, audit log."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from navi_learner.serving.checkpoint import CheckpointMeta, load_checkpoint, save_checkpoint
from navi_learner.serving.registry import ModelRegistry, RegistryError


def make_ckpt(folder: Path, name: str, reward: float, step: int) -> Path:
    m = CheckpointMeta(
        step_id=step,
        episode_count=1,
        reward_ema=reward,
        wall_time_hours=0.0,
        temporal_core="mamba2",
        run_id=f"run-{name}",
        config={},
        obs_shape=[3, 8, 8],
    )
    return save_checkpoint(folder / f"{name}.pt", {"w": torch.full((2,), reward)}, None, m)


def test_promote_rollback_and_audit(tmp_path: Path) -> None:
    reg = ModelRegistry(tmp_path / "models")
    a = make_ckpt(tmp_path, "a", 0.1, 100)
    b = make_ckpt(tmp_path, "b", 0.5, 200)
    c = make_ckpt(tmp_path, "c", 0.3, 300)
    assert reg.promote(a, notes="first", tags=("rl",)).version == "v001"
    assert reg.get("latest").version == "v001"
    assert reg.promote(b).version == "v002"
    assert reg.get("latest").version == "v002"
    # a worse model is registered, but latest stays on the best reward_ema
    assert reg.promote(c).version == "v003"
    assert reg.get("latest").version == "v002"
    assert load_checkpoint(reg.latest_path).meta.reward_ema == 0.5
    # explicit aliases point exactly where asked
    reg.promote("v003", alias="champion")
    assert reg.get("champion").version == "v003"
    reg.promote("v001", alias="champion", notes="older is safer")
    assert reg.get("champion").version == "v001"
    assert reg.rollback("champion").version == "v003"
    assert reg.rollback("latest").version == "v001"
    assert load_checkpoint(reg.latest_path).meta.reward_ema == pytest.approx(0.1)
    with pytest.raises(RegistryError):
        reg.rollback("latest")
    entries = reg.list()
    assert [e.version for e in entries] == ["v001", "v002", "v003"]
    assert entries[0].notes == "first" and entries[0].tags == ("rl",)
    assert all((tmp_path / "models" / e.file).is_file() for e in entries)
    moves = [(r.action, r.alias, r.from_version, r.to_version) for r in reg.audit()]
    assert moves == [
        ("promote", "latest", None, "v001"),
        ("promote", "latest", "v001", "v002"),
        ("promote", "champion", None, "v003"),
        ("promote", "champion", "v003", "v001"),
        ("rollback", "champion", "v001", "v003"),
        ("rollback", "latest", "v002", "v001"),
    ]


def test_versions_are_immutable_copies(tmp_path: Path) -> None:
    reg = ModelRegistry(tmp_path / "models")
    a = make_ckpt(tmp_path, "a", 0.1, 100)
    entry = reg.promote(a)
    make_ckpt(tmp_path, "a", 9.9, 999)  # overwrite the source
    assert load_checkpoint(reg.path(entry.version)).meta.reward_ema == pytest.approx(0.1)


def test_maybe_promote_only_when_better(tmp_path: Path) -> None:
    reg = ModelRegistry(tmp_path / "models")
    assert reg.maybe_promote(make_ckpt(tmp_path, "a", 0.2, 1)) is not None
    assert reg.maybe_promote(make_ckpt(tmp_path, "b", 0.1, 2)) is None
    assert reg.maybe_promote(make_ckpt(tmp_path, "c", 0.3, 3)) is not None
    assert [e.version for e in reg.list()] == ["v001", "v002"]
    assert reg.get("latest").reward_ema == pytest.approx(0.3)


def test_bad_input_is_rejected(tmp_path: Path) -> None:
    reg = ModelRegistry(tmp_path / "models")
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(RegistryError):
        reg.promote(tmp_path / "junk.pt")
    with pytest.raises(RegistryError):
        reg.get("v042")
