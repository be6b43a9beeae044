"""`navi soak`: a short soak of the local stack under overlapping faults holds every check, and the checks
themselves fail on what they are there to catch (a leak, a lost step, a bad file, an uncounted input)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from navi.soak import FAULTS, Life, Record, SoakConfig, checks, table
from navi_learner.config import EngineConfig, TrainConfig
from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint
from navi_learner.serving.registry import ModelRegistry

SHORT_MINUTES = 3.0
"""CI's soak: every fault kind comes within its first nine faults (about 75 s at the default gap)."""


def _good_record() -> Record:
    rec = Record()
    for kind in FAULTS:
        rec.add(kind)
    for name in ("router", "compiler", "env", "learner", "auditor"):
        for i in range(3):  # three lives, flat memory and descriptors
            rec.lives.append(Life(name, 100 + i, 0.0, [(25.0, 200.0 + 0.1 * i, 40, 12)]))
        rec.token_back_s.append((name, 3.0))
    rec.learner_restarts.append(
        {"service": 0, "step_at_kill": 900, "newest_checkpoint": 512, "resumed_at": 512}
    )
    rec.bad_inputs.append({"service": "env", "topic": "navi/env/step", "sent": 11, "counted": 11.0})
    rec.rest.append({"case": "no token", "status": 401, "refused": True, "counted": True})
    rec.bombs.append(
        {"refused": True, "why": "SourceTooLargeError", "output_written": False, "counted": True}
    )
    rec.pauses.append({"paused_s": 12.0, "steps_back_after_s": 0.3, "timeouts": 3})
    rec.promotions["ok"] = 4
    rec.brain_ok = 10
    return rec


def _write_files(root: Path) -> Path:
    """A run checkpoint and a registry holding it, as the learner leaves them; returns the checkpoint."""
    meta = CheckpointMeta(
        step_id=512, episode_count=3, reward_ema=0.1, wall_time_hours=0.0, temporal_core="gru", run_id="r",
        config=TrainConfig(engine=EngineConfig.tiny()).to_dict(), obs_shape=[3, 32, 8],
    )  # fmt: skip
    ckpt = root / "artifacts" / "runs" / "r" / "checkpoints" / "ckpt_step_0000000512.pt"
    save_checkpoint(ckpt, {"w": torch.zeros(4)}, None, meta)
    ModelRegistry(root / "artifacts" / "models").promote(ckpt)
    return ckpt


def _verdicts(report: dict[str, object]) -> dict[str, bool]:
    return {c["name"]: c["ok"] for c in report["checks"]}  # type: ignore[attr-defined,index]


def test_checks_pass_a_clean_record_and_flag_each_failure(tmp_path: Path) -> None:
    cfg = SoakConfig(root=tmp_path)
    ckpt = _write_files(tmp_path)
    answering = {"compiler": True, "env": True, "learner": True, "auditor": True, "dashboard": True}
    clean = checks(cfg, _good_record(), answering)
    assert clean["passed"], table(clean)

    rec = _good_record()
    rec.lives += [Life("env", 200 + i, 0.0, [(25.0, 200.0 + 100.0 * i, 40 + 8 * i, 12)]) for i in range(1, 4)]
    rec.learner_restarts.append(
        {"service": 0, "step_at_kill": 2048, "newest_checkpoint": 1536, "resumed_at": 1024}
    )
    rec.bad_inputs.append({"service": "auditor", "topic": "navi/telemetry", "sent": 11, "counted": 9.0})
    rec.rest.append({"case": "oversized", "status": 413, "refused": True, "counted": False})
    rec.bombs.append({"refused": False, "why": "", "output_written": True, "counted": True})
    rec.promotions["failed"] = 1
    rec.token_back_s.append(("router", None))
    ckpt.write_bytes(ckpt.read_bytes()[:100])  # a truncated checkpoint
    broken = checks(cfg, rec, {**answering, "dashboard": False})
    verdicts = _verdicts(broken)
    assert not broken["passed"]
    failed = {name for name, ok in verdicts.items() if not ok}
    assert failed == {
        "learner steps lost beyond the newest checkpoint",
        "env: memory, fds per restart",
        "checkpoints and registry files load (weights_only)",
        "liveliness token back after a restart",
        "answering at the end",
        "bad messages counted under their topic",
        "bad REST requests refused (4xx) and counted",
        "archive bombs refused and counted, nothing written",
        "promotions during checkpoint writes",
    }, table(broken)


@pytest.mark.integration
@pytest.mark.slow
def test_a_short_soak_of_the_local_stack_holds(tmp_path: Path) -> None:
    """Three minutes of overlapping faults on 2 CPU cores: every kind injected, every check held."""
    out = tmp_path / "soak"
    proc = subprocess.run(
        [sys.executable, "-m", "navi", "soak", "--minutes", str(SHORT_MINUTES), "--out", str(out), "--json"],
        capture_output=True, text=True, timeout=1500,
    )  # fmt: skip
    logs = "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in sorted((out / "stack").glob("*.log")))
    assert proc.stdout.strip(), proc.stderr + logs
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    print(table(report))  # the CI log keeps the table
    assert report == json.loads((out / "soak.json").read_text())
    assert proc.returncode == 0 and report["passed"], table(report) + logs
    kinds = {f["kind"] for f in report["faults"]}
    assert kinds == set(FAULTS)
    killed = {f["service"] for f in report["faults"] if f["kind"] == "kill"}
    assert {"compiler", "env", "learner"} <= killed
    for restart in report["learner_restarts"]:  # resumed exactly at the newest checkpoint on disk
        assert restart["resumed_at"] == restart["newest_checkpoint"] > 0 or restart["newest_checkpoint"] == 0
    assert all(b["refused"] and not b["output_written"] for b in report["bombs"])
