"""`navi stack up|down|status` as local processes on a CPU-only machine (tiny corpus, a few actors)."""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

import httpx
import pytest
from services_testlib import NAVI, free_port

from navi_mesh.stack import StackConfig, StackError, read_states, service_specs, stop_all, up, wait_for_tokens

pytestmark = pytest.mark.integration


def test_specs_are_the_compose_commands() -> None:
    cfg = StackConfig(navi=("navi",))
    names = [s.name for s in service_specs(cfg, with_auditor=True)]
    assert names == ["router", "compiler", "env", "learner", "auditor"]
    for spec in service_specs(cfg, with_auditor=True):
        assert spec.argv[:3] == ("navi", "serve", spec.name)


def test_stack_up_status_down(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from navi_compiler.scenes import generate_corpus
    from navi_env.corpus import build_corpus

    monkeypatch.chdir(tmp_path)
    corpus = tmp_path / "corpus"
    build_corpus(generate_corpus(tmp_path / "sources", 1, 0), corpus, resolution=64)
    for name, value in {
        "NAVI_API_TOKEN": "",
        "NAVI_ARTIFACTS_DIR": str(tmp_path / "artifacts"),
        "NAVI_AZIMUTH_BINS": "32",
        "NAVI_ELEVATION_BINS": "8",
        "OMP_NUM_THREADS": "1",
    }.items():
        monkeypatch.setenv(name, value)
    cfg = StackConfig(
        root=tmp_path / "stack",
        router_port=free_port(),
        api_port=free_port(),
        compiler_metrics_port=free_port(),
        env_metrics_port=free_port(),
        corpus=corpus,
        actors=2,
        env_actors=1,
        device="cpu",
        auditor=False,
        navi=NAVI,
    )
    said: list[str] = []
    try:
        states = up(cfg, 120.0, lambda line: None, said.append)
        assert [s.name for s in states] == ["router", "compiler", "env", "learner"]
        assert wait_for_tokens(cfg.router_port, ["router", "compiler", "env", "learner"], 60.0) == []
        assert all(s.running for s in read_states(cfg.root))
        # The generated token is printed once, kept private on disk, and guards the control plane.
        token_file = cfg.root / "api_token"
        token = token_file.read_text().strip()
        assert len(token) >= 24 and sum(token in line for line in said) == 1
        assert stat.S_IMODE(os.stat(token_file).st_mode) == 0o600
        health = httpx.get(f"http://127.0.0.1:{cfg.api_port}/healthz", timeout=5.0)
        assert health.json()["mutations_enabled"] is True
        wrong = httpx.post(
            f"http://127.0.0.1:{cfg.api_port}/models/rollback",
            json={"alias": "champion"},
            headers={"Authorization": "Bearer wrong"},
        )
        assert wrong.status_code == 403
        with pytest.raises(StackError, match="already running"):
            up(cfg, 1.0, lambda line: None, said.append)
    finally:
        t0 = time.monotonic()
        stopped = stop_all(cfg.root, 30.0)
        took = time.monotonic() - t0
    assert [s.name for s in stopped] == ["router", "compiler", "env", "learner"]
    assert not any(s.running for s in stopped)
    assert read_states(cfg.root) == []
    assert took < 25.0  # every service left on SIGTERM, none needed the SIGKILL


def test_status_without_a_stack_says_so(tmp_path: Path) -> None:
    import json
    import subprocess
    import sys

    env = {**os.environ, "NAVI_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}"}
    out = subprocess.run(
        [sys.executable, "-m", "navi", "stack", "status", "--json", "--timeout", "0.5"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    status = json.loads(out.stdout)
    assert status["processes"] == [] and status["alive"] == [] and status["router_error"]
