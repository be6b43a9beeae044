"""`navi stack up|down|status` as local processes on a CPU-only machine, starting from no corpus.

Bring-up: every service passes its health check within 15 s while the corpus does not exist; the
learner then builds the procedural default corpus over compile jobs on the compiler worker, its
progress shows in /healthz, in Prometheus and on the dashboard, and training starts when it is ready.
Every socket the stack opens is bound to 127.0.0.1.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from services_testlib import NAVI, free_port, small_cpu_stack, wait_for

from navi.stack import (
    StackConfig,
    StackError,
    has_auditor,
    read_states,
    service_specs,
    stop_all,
    up,
    wait_for_tokens,
)

pytestmark = pytest.mark.integration

HEALTHY_WITHIN_S = 15.0
"""The bound the README promises: each service answers its health check within 15 s on a 2-core machine."""


def test_specs_are_the_compose_commands() -> None:
    cfg = StackConfig(navi=("navi",))
    names = [s.name for s in service_specs(cfg, with_auditor=True)]
    assert names == ["router", "compiler", "env", "learner", "auditor"]
    for spec in service_specs(cfg, with_auditor=True):
        assert spec.argv[:3] == ("navi", "serve", spec.name)
        host_option = {"router": "--listen", "learner": "--host", "auditor": "--host"}.get(
            spec.name, "--metrics-host"
        )
        value = spec.argv[spec.argv.index(host_option) + 1]
        assert value.startswith(("127.0.0.1", "tcp/127.0.0.1:")), (spec.name, value)
    compiler = service_specs(cfg, with_auditor=False)[1].argv
    assert compiler[compiler.index("--device") + 1] == "auto"  # the GPU compile engine on a CUDA host
    wide = service_specs(StackConfig(navi=("navi",), host="0.0.0.0"), with_auditor=True)
    assert wide[0].argv[-1] == "tcp/0.0.0.0:7447" and "0.0.0.0" in wide[3].argv


def scrape(url: str) -> dict[str, float]:
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    return {
        s.name + json.dumps(s.labels, sort_keys=True) if s.labels else s.name: s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def listening(ports: set[int]) -> dict[int, set[str]]:
    """Local addresses of the LISTEN sockets on the given ports (from /proc/net/tcp and tcp6)."""
    found: dict[int, set[str]] = {p: set() for p in ports}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            address, port_hex = fields[1].rsplit(":", 1)
            if fields[3] == "0A" and int(port_hex, 16) in ports:
                found[int(port_hex, 16)].add(address)
    return found


def healthz(port: int) -> dict[str, Any]:
    try:
        body: dict[str, Any] = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2.0).json()
        return body
    except httpx.HTTPError:
        return {}


def test_stack_up_without_a_corpus_builds_it_over_compile_jobs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = small_cpu_stack(tmp_path, monkeypatch)
    corpus = cfg.corpus
    with_auditor = has_auditor()
    names = ["router", "compiler", "env", "learner", *(["auditor"] if with_auditor else [])]
    said: list[str] = []
    try:
        started = up(cfg, 60.0, lambda line: None, said.append)
        assert [s.name for s in started.states] == names
        slowest = max(started.healthy_after_s.values(), key=lambda v: float("inf") if v is None else v)
        assert all(v is not None for v in started.healthy_after_s.values()), started.healthy_after_s
        assert slowest is not None and slowest <= HEALTHY_WITHIN_S, started.healthy_after_s
        print(f"healthy after (s): {json.dumps(started.healthy_after_s)}")

        # The corpus is built in the background; /healthz follows it to the end.
        states_seen: list[str] = []

        def corpus_ready() -> bool:
            corpus_state = (healthz(cfg.api_port).get("corpus") or {}).get("state", "")
            if corpus_state and (not states_seen or states_seen[-1] != corpus_state):
                states_seen.append(corpus_state)
            return corpus_state == "ready"

        wait_for(corpus_ready, 120.0, "the corpus build", poll_s=0.2)
        health = healthz(cfg.api_port)
        progress = health["corpus"]
        assert progress["scenes_total"] == 2 and progress["scenes_ready"] + progress["rejected"] == 2
        assert progress["scenes_ready"] >= 1 and progress["error"] == ""
        assert states_seen[-1] == "ready" and set(states_seen) <= {"missing", "waiting", "building", "ready"}
        manifest = json.loads((corpus / "manifest.json").read_text())
        assert len(manifest["scenes"]) == progress["scenes_ready"]
        assert not list(corpus.parent.glob(".default.*"))  # no build or source folder left behind

        # Prometheus: the learner's gauges, the compiler's job counter (the same path as `--remote`).
        learner_metrics = scrape(f"http://127.0.0.1:{cfg.api_port}/metrics")
        assert learner_metrics["navi_corpus_scenes_ready"] == progress["scenes_ready"]
        assert learner_metrics["navi_corpus_scenes_planned"] == 2.0
        assert learner_metrics["navi_corpus_ready"] == 1.0
        compiler_metrics = scrape(f"http://127.0.0.1:{cfg.compiler_metrics_port}/metrics")
        assert compiler_metrics['navi_compile_jobs_total{"outcome": "ok"}'] == 2.0

        # Training starts once the corpus is ready; the env serves once it appears.
        wait_for(lambda: healthz(cfg.api_port).get("phase") == "training", 60.0, "training")
        assert healthz(cfg.api_port)["actors"] == 2 and healthz(cfg.api_port)["run_id"]
        assert wait_for_tokens(cfg.router_port, names, 60.0) == []
        if with_auditor:
            dashboard = f"http://127.0.0.1:{cfg.auditor_port}/api/state"
            wait_for(lambda: httpx.get(dashboard).json()["mode"] == "TRAINING", 60.0, "the dashboard")
            shown = httpx.get(dashboard).json()
            assert shown["actors"] == 2 and shown["run_id"] == healthz(cfg.api_port)["run_id"]
            assert shown["corpus"]["ready"] == progress["scenes_ready"] and shown["corpus"]["planned"] == 2
            # Actor 0's trail over the floor plan of the scene it flies in (a scene of this corpus).
            scene_names = {scene["name"] for scene in manifest["scenes"]}
            wait_for(lambda: httpx.get(dashboard).json()["plan_scene"] in scene_names, 30.0, "a floor plan")
            assert httpx.get(dashboard).json()["trail_points"] > 0

        # `navi stack status` joins the processes, the live tokens and the learner's progress.
        status = subprocess.run(
            [*NAVI, "stack", "status", "--json"], cwd=tmp_path, capture_output=True, text=True, timeout=60,
            env={**os.environ, "NAVI_ZENOH_CONNECT": f"tcp/127.0.0.1:{cfg.router_port}"},
        )  # fmt: skip
        assert status.returncode == 0, status.stderr
        shown_status = json.loads(status.stdout)
        assert [p["name"] for p in shown_status["processes"] if p["running"]] == names
        assert shown_status["learner"]["phase"] == "training"
        assert shown_status["learner"]["corpus"]["state"] == "ready"

        # Safe defaults: every listening socket of the stack is on 127.0.0.1 (0100007F) only.
        ports = {cfg.router_port, cfg.api_port, cfg.compiler_metrics_port, cfg.env_metrics_port}
        ports |= {cfg.auditor_port} if with_auditor else set()
        bound = listening(ports)
        assert bound == {p: {"0100007F"} for p in ports}, bound

        # The generated token is printed once, kept private on disk, and guards the control plane.
        token_file = cfg.root / "api_token"
        token = token_file.read_text().strip()
        assert len(token) >= 24 and sum(token in line for line in said) == 1
        assert stat.S_IMODE(os.stat(token_file).st_mode) == 0o600
        assert healthz(cfg.api_port)["mutations_enabled"] is True
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
    assert [s.name for s in stopped] == names
    assert not any(s.running for s in stopped)
    assert read_states(cfg.root) == []
    assert took < 25.0  # every service left on SIGTERM, none needed the SIGKILL


def test_status_without_a_stack_says_so(tmp_path: Path) -> None:
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
    assert status["learner"] is None
