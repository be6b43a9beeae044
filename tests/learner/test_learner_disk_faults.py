"""A full disk and damaged files: training goes on past checkpoint and registry writes that fail, every
file left on disk loads, and a start after damage recovers the last good state (checkpoint checksums,
resume from a run folder, the registry's recover) without overwriting or deleting anything."""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import stat
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from navi_learner.config import EngineConfig, PPOConfig, TrainConfig
from navi_learner.envs.toy import ToyEnv
from navi_learner.ppo.train import train
from navi_learner.serving import checkpoint as ck
from navi_learner.serving.checkpoint import CheckpointError, CheckpointMeta, load_checkpoint, save_checkpoint
from navi_learner.serving.registry import LATEST, ModelRegistry, RegistryError, sha256_of
from navi_mesh.metrics import REGISTRY

pytestmark = pytest.mark.usefixtures("single_thread")

ACTORS, T = 8, 16
PER_UPDATE = ACTORS * T  # env steps of one update


def config(updates: int, **kw: Any) -> TrainConfig:
    """A tiny run that checkpoints after every update."""
    return TrainConfig(
        n_actors=ACTORS,
        rollout_length=T,
        total_steps=updates * PER_UPDATE,
        engine=EngineConfig.tiny(),
        ppo=PPOConfig(num_minibatches=1, bptt_chunk=T, ppo_epochs=1),
        checkpoint_every=PER_UPDATE,
        log_every=1,
        **{"keep_checkpoints": 100, **kw},
    )


def write_errors(what: str) -> float:
    return REGISTRY.get_sample_value("navi_write_errors_total", {"what": what}) or 0.0


class DiskFull:
    """os.write and os.fsync raise ENOSPC for regular files under `roots` while `full` is set (or at
    the `fail_at`-th such call): what a full disk does to a write (after part of the data went in) and
    to the flush that makes it durable. Other files write normally."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, *roots: Path) -> None:
        self.roots = [str(r.resolve()) + os.sep for r in roots]
        self.full = False
        self.fail_at = 0  # with full unset: the call (counted from 1) that fails; 0 = none
        self.calls = 0
        self.raised = 0
        real_write, real_fsync = os.write, os.fsync

        def fails(fd: Any) -> bool:
            fd = fd if isinstance(fd, int) else fd.fileno()
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                return False
            if not any(os.readlink(f"/proc/self/fd/{fd}").startswith(r) for r in self.roots):
                return False
            self.calls += 1
            if self.full or self.calls == self.fail_at:
                self.raised += 1
                return True
            return False

        def write(fd: int, data: Any) -> int:
            if fails(fd):  # the blocks that were free take the first half, then the disk is full
                real_write(fd, memoryview(data)[: len(data) // 2])
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real_write(fd, data)

        def fsync(fd: Any) -> None:
            if fails(fd):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real_fsync(fd)

        monkeypatch.setattr(os, "write", write)
        monkeypatch.setattr(os, "fsync", fsync)


class At:
    """A training monitor that calls `act(step_id)` after every update (before that update's checkpoint)."""

    status = ""

    def __init__(self, act: Callable[[int], None]) -> None:
        self.act = act

    def __call__(self, policy: Any, step_id: int, train_s: float) -> bool:
        self.act(step_id)
        return False


def temp_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def steps_on_disk(folder: Path) -> list[int]:
    """The step of every checkpoint in a folder, each loaded with plain torch.load(weights_only=True)
    and verified by load_checkpoint."""
    steps = []
    for path in sorted(folder.glob("ckpt_step_*.pt")):
        assert torch.load(path, map_location="cpu", weights_only=True)["format_version"] == 3
        steps.append(load_checkpoint(path).meta.step_id)
    return steps


def test_training_goes_on_through_a_full_disk_and_checkpoints_again_when_space_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    run_dir, models = tmp_path / "run", tmp_path / "models"
    disk = DiskFull(monkeypatch, run_dir / "checkpoints", models)

    def weather(step: int) -> None:  # the disk is full for the checkpoints of updates 3 and 4
        disk.full = step in (3 * PER_UPDATE, 4 * PER_UPDATE)

    before = write_errors("checkpoint")
    with caplog.at_level(logging.ERROR, logger="navi_learner.ppo.learner"):
        result = train(
            ToyEnv(ACTORS, seed=1),
            config(6),
            run_dir=run_dir,
            registry=ModelRegistry(models),
            monitor=At(weather),
            progress=False,
        )
    assert result.step_id == 6 * PER_UPDATE and not result.interrupted
    assert disk.raised == 2 and write_errors("checkpoint") - before == 2
    good = run_dir / "checkpoints" / ck.checkpoint_name(2 * PER_UPDATE)
    assert [r.getMessage() for r in caplog.records] == [
        f"checkpoint {ck.checkpoint_name(step * PER_UPDATE)} not written: [Errno 28] No space left on "
        f"device; training goes on, the last good checkpoint is {good}"
        for step in (3, 4)
    ]
    assert steps_on_disk(run_dir / "checkpoints") == [s * PER_UPDATE for s in (1, 2, 5, 6)]
    assert result.final_checkpoint.name == ck.checkpoint_name(6 * PER_UPDATE)  # newer than the failures
    assert temp_files(run_dir / "checkpoints") == []
    assert result.promoted == "v001" and load_checkpoint(ModelRegistry(models).path(LATEST)).meta.step_id == (
        6 * PER_UPDATE
    )
    train_log = (run_dir / "logs" / "train.log").read_text()
    assert train_log.count("not written: [Errno 28] No space left on device") == 2


def make_ckpt(folder: Path, name: str, reward: float, step: int) -> Path:
    meta = CheckpointMeta(step, 1, reward, 0.0, "gru", f"run-{name}", {}, [3, 8, 8])
    weights = {"w": torch.full((64,), reward), "b": torch.arange(8, dtype=torch.float32)}  # (64,), (8,)
    return save_checkpoint(folder / f"{name}.pt", weights, None, meta)


def assert_registry_consistent(reg: ModelRegistry) -> None:
    """Every listed version file is complete, aliases and history name listed versions, every audit line
    parses, no temporary file and no version file outside the index."""
    index = json.loads(reg.index_path.read_text())
    listed = {v["file"] for v in index["versions"]}
    for v in index["versions"]:
        assert sha256_of(reg.root / v["file"]) == v["sha256"], v["version"]
        load_checkpoint(reg.root / v["file"])
    assert {p.name for p in reg.root.glob("v*.pt")} == listed
    known = {v["version"] for v in index["versions"]}
    assert set(index["aliases"].values()) <= known
    assert all(h in known for hist in index["history"].values() for h in hist)
    for line in reg.audit_path.read_text().splitlines():
        json.loads(line)
    assert temp_files(reg.root) == []


def test_the_final_promotion_fails_on_a_full_disk_and_the_registry_keeps_its_last_good_state(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    reg = ModelRegistry(tmp_path / "models")
    reg.promote(make_ckpt(tmp_path, "old", -1e9, 1))  # v001: any run beats it
    index_before = reg.index_path.read_bytes()
    disk = DiskFull(monkeypatch, reg.root)
    disk.full = True
    before = write_errors("registry")
    with caplog.at_level(logging.ERROR, logger="navi_learner.ppo.promotion"):
        result = train(
            ToyEnv(ACTORS, seed=1), config(2), run_dir=tmp_path / "run", registry=reg, progress=False
        )
    assert result.step_id == 2 * PER_UPDATE and result.promoted is None
    assert write_errors("registry") - before == 1
    assert [r.getMessage() for r in caplog.records] == [
        f"model registry {reg.root}: {result.final_checkpoint.name} not promoted: [Errno 28] No space left "
        "on device"
    ]
    assert reg.index_path.read_bytes() == index_before
    assert_registry_consistent(reg)
    assert reg.recover() == []
    disk.full = False  # space returns: the next promotion takes the next number
    assert reg.promote(result.final_checkpoint).version == "v002"
    assert_registry_consistent(reg)


def test_a_registry_write_that_fails_at_any_point_leaves_a_consistent_registry(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Promotions of a new version, with the n-th write under the registry failing, for every n a
    promotion makes (the version file, the index, the audit line, the latest.pt copy)."""
    reg = ModelRegistry(tmp_path / "models")
    reg.promote(make_ckpt(tmp_path, "a", 0.1, 1))
    disk = DiskFull(monkeypatch, reg.root)
    n, promoted = 0, False
    while not promoted:
        n += 1
        disk.calls, disk.fail_at = 0, n
        try:
            reg.promote(make_ckpt(tmp_path, f"n{n}", 0.1 + n, 1 + n))
            promoted = True
        except OSError as err:
            assert err.errno == errno.ENOSPC
        disk.fail_at = 0
        assert_registry_consistent(reg)
        reg.recover()  # what the learner service runs at start
        assert_registry_consistent(reg)
        best = max(reg.list(), key=lambda e: e.reward_ema)
        assert reg.get(LATEST) == best and sha256_of(reg.latest_path) == best.sha256
    assert n >= 4, n  # the version file, the index, the audit line and latest.pt each failed once


def test_atomic_write_leaves_no_temporary_file_when_write_fsync_or_replace_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = make_ckpt(tmp_path, "ckpt", 0.5, 100)
    meta = CheckpointMeta(200, 1, 0.9, 0.0, "gru", "r", {}, [3, 8, 8])

    def half_save(obj: Any, f: Any) -> None:  # half the data, then the disk is full
        f.write(bytes(1000))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def enospc(*args: Any) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    for fail in ("write", "fsync", "replace"):
        with monkeypatch.context() as m:
            if fail == "write":
                m.setattr(torch, "save", half_save)
            elif fail == "fsync":
                DiskFull(m, tmp_path).full = True
            else:
                m.setattr(ck.os, "replace", enospc)
            with pytest.raises(OSError) as raised:
                save_checkpoint(path, {"w": torch.ones(3)}, None, meta)
        assert raised.value.errno == errno.ENOSPC
        assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"], fail
        assert load_checkpoint(path).meta.step_id == 100


def flip_a_weight_byte(path: Path, tensor: torch.Tensor) -> None:
    """Flip one bit inside a tensor's stored bytes (found by content), as a bad disk sector would."""
    raw = bytearray(path.read_bytes())
    at = raw.find(tensor.numpy().tobytes())
    assert at >= 0
    raw[at + 5] ^= 0x04
    path.write_bytes(bytes(raw))


def test_a_flipped_byte_fails_the_checksum_that_torch_does_not_check(tmp_path: Path) -> None:
    path = make_ckpt(tmp_path, "c", 0.5, 10)
    assert len(load_checkpoint(path).meta.sha256) == 64
    flip_a_weight_byte(path, torch.full((64,), 0.5))
    torch.load(path, weights_only=True)  # torch's loader reads it without complaint
    with pytest.raises(CheckpointError, match=re.escape(f"{path} fails its checksum")):
        load_checkpoint(path)


def test_checkpoints_without_a_checksum_still_load(tmp_path: Path) -> None:
    path = make_ckpt(tmp_path, "c", 0.5, 10)
    payload = torch.load(path, weights_only=True)
    del payload["meta"]["sha256"]  # as written before checkpoints had one
    torch.save(payload, path)
    loaded = load_checkpoint(path)
    assert loaded.meta.sha256 == "" and loaded.meta.step_id == 10
    assert torch.equal(loaded.model["w"], torch.full((64,), 0.5))


def test_resume_from_a_run_folder_takes_the_newest_checkpoint_that_verifies(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    first = train(ToyEnv(ACTORS, seed=1), config(3), run_dir=tmp_path / "r1", progress=False)
    folder = tmp_path / "r1" / "checkpoints"
    newest = folder / ck.checkpoint_name(3 * PER_UPDATE)
    assert first.final_checkpoint == newest
    weight = next(v for v in load_checkpoint(newest).model.values() if v.numel() >= 64)
    flip_a_weight_byte(newest, weight)
    bad_bytes = newest.read_bytes()
    with caplog.at_level(logging.ERROR, logger="navi_learner.serving.checkpoint"):
        second = train(
            ToyEnv(ACTORS, seed=2),
            config(4),
            run_dir=tmp_path / "r2",
            resume_from=tmp_path / "r1",
            progress=False,
        )
    skipped = [r.getMessage() for r in caplog.records]
    assert skipped == [
        f"{newest} fails its checksum: the file changed after it was written (skipped: an older checkpoint "
        "is tried)"
    ]
    manifest = json.loads((tmp_path / "r2" / "manifests" / "run.json").read_text())
    assert manifest["resume_from"] == str(folder / ck.checkpoint_name(2 * PER_UPDATE))
    assert second.step_id == 4 * PER_UPDATE
    assert newest.read_bytes() == bad_bytes  # the bad file stays as it was


def registry_with_history(tmp_path: Path) -> ModelRegistry:
    reg = ModelRegistry(tmp_path / "models")
    reg.promote(make_ckpt(tmp_path, "a", 0.1, 100), notes="first")
    reg.promote(make_ckpt(tmp_path, "b", 0.5, 200))
    reg.promote(make_ckpt(tmp_path, "c", 0.3, 300))
    reg.promote("v003", alias="champion")
    reg.promote("v001", alias="champion", notes="older is safer")
    return reg


def test_a_truncated_registry_index_is_moved_aside_and_rebuilt(tmp_path: Path) -> None:
    reg = registry_with_history(tmp_path)
    want = json.loads(reg.index_path.read_text())
    raw = reg.index_path.read_bytes()
    reg.index_path.write_bytes(raw[: len(raw) // 2])  # a torn index
    with pytest.raises(RegistryError, match=r"registry\.json is unreadable"):
        reg.list()
    done = reg.recover()
    assert len(done) == 1 and done[0].startswith("registry.json is unreadable (")
    aside = [p for p in reg.root.iterdir() if p.name.startswith("registry.json.corrupt-")]
    assert len(aside) == 1 and aside[0].name in done[0] and aside[0].read_bytes() == raw[: len(raw) // 2]
    got = json.loads(reg.index_path.read_text())
    assert got["aliases"] == want["aliases"] and got["history"] == want["history"]
    exact = ("version", "file", "step_id", "reward_ema", "temporal_core", "run_id", "created_at", "sha256")
    assert [{k: v[k] for k in exact} for v in got["versions"]] == [
        {k: v[k] for k in exact} for v in want["versions"]
    ]
    assert reg.get("v001").notes == "first"
    assert reg.rollback("champion").version == "v003"  # the history came back too
    assert reg.recover() == []
    assert_registry_consistent(reg)


def test_a_version_file_with_a_bad_checksum_is_moved_aside_and_latest_moves_to_the_best_good_one(
    tmp_path: Path,
) -> None:
    reg = registry_with_history(tmp_path)
    assert reg.get(LATEST).version == "v002"
    bad = reg.root / "v002.pt"
    flip_a_weight_byte(bad, torch.full((64,), 0.5))
    bad_bytes = bad.read_bytes()
    done = reg.recover()
    assert len(done) == 1 and done[0].startswith("v002.pt fails its sha256")
    assert "latest -> v003" in done[0]
    aside = [p for p in reg.root.iterdir() if p.name.startswith("v002.pt.corrupt-")]
    assert len(aside) == 1 and aside[0].read_bytes() == bad_bytes  # renamed, not deleted or rewritten
    assert [e.version for e in reg.list()] == ["v001", "v003"]
    assert reg.get(LATEST).version == "v003"
    assert load_checkpoint(reg.latest_path).meta.reward_ema == pytest.approx(0.3)
    last = reg.audit()[-1]
    assert (last.action, last.alias, last.from_version, last.to_version) == (
        "recover",
        LATEST,
        "v002",
        "v003",
    )
    assert reg.recover() == []
    assert_registry_consistent(reg)
    assert reg.promote(make_ckpt(tmp_path, "d", 0.2, 400)).version == "v004"  # v002's number stays taken


class SmallDisk:
    """A 2 MiB tmpfs (room for about five checkpoints of the tiny engine) that a ballast file fills, where
    this machine lets the test mount one; elsewhere the same folder with ENOSPC injected while the
    ballast "is there" (DiskFull), so the scenario and its assertions run on every machine."""

    def __init__(self, root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        self.root = root
        self.ballast = root / "ballast"
        root.mkdir()
        try:
            subprocess.run(
                ["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(root)], check=True, capture_output=True
            )
            self.injected: DiskFull | None = None
        except (OSError, subprocess.CalledProcessError):
            self.injected = DiskFull(monkeypatch, root)
        print(
            f"full disk: {'a real 2 MiB tmpfs' if self.injected is None else 'injected ENOSPC (no mount allowed)'}"
        )

    def fill(self) -> None:
        """Write zeros into the ballast until the file system is full."""
        if self.injected is not None:
            self.injected.full = True
            return
        block = bytes(1 << 16)
        with self.ballast.open("wb") as f:
            try:
                while True:
                    f.write(block)
                    f.flush()
            except OSError as err:
                assert err.errno == errno.ENOSPC

    def free(self) -> None:
        if self.injected is not None:
            self.injected.full = False
        else:
            self.ballast.unlink()


@pytest.fixture
def small_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[SmallDisk]:
    disk = SmallDisk(tmp_path / "disk", monkeypatch)
    try:
        yield disk
    finally:
        if disk.injected is None:
            subprocess.run(["umount", str(disk.root)], check=True)


def test_training_on_a_really_full_file_system(tmp_path: Path, small_disk: SmallDisk) -> None:
    run_dir, models = tmp_path / "run", small_disk.root / "models"
    (small_disk.root / "checkpoints").mkdir()
    run_dir.mkdir()
    (run_dir / "checkpoints").symlink_to(small_disk.root / "checkpoints")

    def weather(step: int) -> None:  # full from update 3's checkpoint until update 5's
        if step == 3 * PER_UPDATE:
            small_disk.fill()
        elif step == 5 * PER_UPDATE:
            small_disk.free()

    before = write_errors("checkpoint")
    result = train(
        ToyEnv(ACTORS, seed=1),
        config(6, keep_checkpoints=2),
        run_dir=run_dir,
        registry=ModelRegistry(models),
        monitor=At(weather),
        progress=False,
    )
    assert result.step_id == 6 * PER_UPDATE
    assert write_errors("checkpoint") - before == 2
    assert steps_on_disk(run_dir / "checkpoints") == [5 * PER_UPDATE, 6 * PER_UPDATE]
    assert temp_files(run_dir / "checkpoints") == []
    assert result.promoted == "v001"
    assert_registry_consistent(ModelRegistry(models))


def test_the_newest_good_checkpoint_of_a_runs_folder_is_found_across_runs(tmp_path: Path) -> None:
    """What a learner started with --resume-latest resumes from: the highest step over every run's
    checkpoints that verifies; a newer one with a flipped byte is skipped, and none at all gives None."""
    runs = tmp_path / "runs"
    assert ck.newest_good_checkpoint(runs, ck.RUN_CHECKPOINTS) is None
    older = make_ckpt(runs / "a" / "checkpoints", ck.checkpoint_name(300)[:-3], 0.1, 300)
    good = make_ckpt(runs / "b" / "checkpoints", ck.checkpoint_name(500)[:-3], 0.2, 500)
    bad = make_ckpt(runs / "a" / "checkpoints", ck.checkpoint_name(700)[:-3], 0.3, 700)
    assert ck.newest_good_checkpoint(runs, ck.RUN_CHECKPOINTS) == bad
    flip_a_weight_byte(bad, torch.full((64,), 0.3))
    assert ck.newest_good_checkpoint(runs, ck.RUN_CHECKPOINTS) == good != older
