"""`navi stack up|down|status` as local processes on a CPU-only machine, starting from no corpus, run as
the commands a user types.

Bring-up: every service passes its health check while the corpus does not exist; the learner then
builds the procedural default corpus over compile jobs on the compiler worker, its progress shows in
/healthz, in Prometheus and on the dashboard, and training starts when it is ready. Every socket the
stack opens is bound to 127.0.0.1. `navi stack down` stops every service with SIGTERM and leaves no
process, pid file or listening port behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from services_testlib import NAVI, ReservedPort, small_cpu_stack, wait_for

from navi.stack import (
    StackConfig,
    has_auditor,
    is_running,
    read_states,
    service_specs,
    stop_all,
    wait_for_tokens,
)

pytestmark = pytest.mark.integration


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


def stack_command(folder: Path, *args: str, timeout_s: float = 600.0) -> subprocess.CompletedProcess[str]:
    """`navi stack ARGS...` run in `folder` as a user would (a time-out bounds a hang only)."""
    return subprocess.run(
        [*NAVI, "stack", *args], cwd=folder, capture_output=True, text=True, timeout=timeout_s
    )


def test_stack_up_without_a_corpus_builds_it_over_compile_jobs_and_down_stops_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with contextlib.ExitStack() as reserved:
        cfg = small_cpu_stack(tmp_path, monkeypatch, reserved)
        corpus = cfg.corpus
        with_auditor = has_auditor()
        names = ["router", "compiler", "env", "learner", *(["auditor"] if with_auditor else [])]
        ports = {cfg.router_port, cfg.api_port, cfg.compiler_metrics_port, cfg.env_metrics_port}
        ports |= {cfg.auditor_port} if with_auditor else set()
        try:
            up = stack_command(
                tmp_path, "up", "--corpus", str(corpus.relative_to(tmp_path)), "--actors", str(cfg.actors),
                "--env-actors", str(cfg.env_actors), "--device", cfg.device,
                "--router-port", str(cfg.router_port), "--api-port", str(cfg.api_port),
                "--auditor-port", str(cfg.auditor_port), "--compiler-metrics-port", str(cfg.compiler_metrics_port),
                "--env-metrics-port", str(cfg.env_metrics_port), "--corpus-scenes", str(cfg.corpus_scenes),
                "--corpus-resolution", str(cfg.corpus_resolution), "--wait", "600",
            )  # fmt: skip
            assert up.returncode == 0, up.stderr
            started = re.findall(r"^started (\w+)\s+pid (\d+)", up.stderr, re.M)
            assert [name for name, _ in started] == names, up.stderr
            # `up` returns once every service passed its health check (the corpus does not exist yet)
            assert sorted(re.findall(r"^(\w+)\s+healthy after", up.stderr, re.M)) == sorted(names), up.stderr
            assert "did not pass its health check" not in up.stderr
            assert f"the corpus {corpus.relative_to(tmp_path)} is being built in the background" in up.stderr
            assert [p.name for p in read_states(cfg.root) if p.running] == names

            # The corpus is built in the background; /healthz follows it to the end.
            states_seen: list[str] = []

            def corpus_ready() -> bool:
                corpus_state = (healthz(cfg.api_port).get("corpus") or {}).get("state", "")
                if corpus_state and (not states_seen or states_seen[-1] != corpus_state):
                    states_seen.append(corpus_state)
                return corpus_state == "ready"

            wait_for(corpus_ready, 600.0, "the corpus build", poll_s=0.2)
            health = healthz(cfg.api_port)
            progress = health["corpus"]
            assert progress["scenes_total"] == 2 and progress["scenes_ready"] + progress["rejected"] == 2
            assert progress["scenes_ready"] >= 1 and progress["error"] == ""
            assert states_seen[-1] == "ready" and set(states_seen) <= {
                "missing",
                "waiting",
                "building",
                "ready",
            }
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
            wait_for(lambda: healthz(cfg.api_port).get("phase") == "training", 600.0, "training")
            assert healthz(cfg.api_port)["actors"] == 2 and healthz(cfg.api_port)["run_id"]
            assert wait_for_tokens(cfg.router_port, names, 600.0) == []
            if with_auditor:
                dashboard = f"http://127.0.0.1:{cfg.auditor_port}/api/state"
                wait_for(lambda: httpx.get(dashboard).json()["mode"] == "TRAINING", 600.0, "the dashboard")
                shown = httpx.get(dashboard).json()
                assert shown["actors"] == 2 and shown["run_id"] == healthz(cfg.api_port)["run_id"]
                assert (
                    shown["corpus"]["ready"] == progress["scenes_ready"] and shown["corpus"]["planned"] == 2
                )
                # Actor 0's trail over the floor plan of the scene it flies in (a scene of this corpus).
                scene_names = {scene["name"] for scene in manifest["scenes"]}
                wait_for(
                    lambda: httpx.get(dashboard).json()["plan_scene"] in scene_names, 600.0, "a floor plan"
                )
                assert httpx.get(dashboard).json()["trail_points"] > 0

            # `navi stack status` joins the processes, the live tokens and the learner's progress.
            monkeypatch.setenv("NAVI_ZENOH_CONNECT", f"tcp/127.0.0.1:{cfg.router_port}")
            status = stack_command(tmp_path, "status", "--json", "--timeout", "30")
            assert status.returncode == 0, status.stderr
            shown_status = json.loads(status.stdout)
            assert [p["name"] for p in shown_status["processes"] if p["running"]] == names
            assert {key.split("/")[2] for key in shown_status["alive"]} == set(names)
            assert shown_status["learner"]["phase"] == "training"
            assert shown_status["learner"]["corpus"]["state"] == "ready"

            # Safe defaults: every listening socket of the stack is on 127.0.0.1 (0100007F) only.
            bound = listening(ports)
            assert bound == {p: {"0100007F"} for p in ports}, bound

            # The generated token is printed once, kept private on disk, and guards the control plane.
            token_file = cfg.root / "api_token"
            token = token_file.read_text().strip()
            assert len(token) >= 24 and sum(token in line for line in up.stdout.splitlines()) == 1
            assert stat.S_IMODE(os.stat(token_file).st_mode) == 0o600
            assert healthz(cfg.api_port)["mutations_enabled"] is True
            wrong = httpx.post(
                f"http://127.0.0.1:{cfg.api_port}/models/rollback",
                json={"alias": "champion"},
                headers={"Authorization": "Bearer wrong"},
            )
            assert wrong.status_code == 403
            again = stack_command(tmp_path, "up", "--wait", "1")
            assert again.returncode == 2 and "already running" in again.stderr, again.stderr

            # Every service leaves on SIGTERM: with a grace far past the command's time-out, a service that
            # needed the SIGKILL would hang `down` until the time-out fails the test.
            down = stack_command(tmp_path, "down", "--grace", "3600", timeout_s=600.0)
            assert down.returncode == 0, down.stderr
            stopped = re.findall(r"^(\w+)\s+pid (\d+)\s+(stopped|STILL RUNNING)$", down.stdout, re.M)
            assert [(name, state) for name, _, state in stopped] == [(name, "stopped") for name in names], (
                down.stdout
            )
            assert {int(pid) for _, pid in started} == {int(pid) for _, pid, _ in stopped}
            assert not any(is_running(int(pid)) for _, pid in started)
            assert read_states(cfg.root) == [] and not list(cfg.root.glob("*.pid"))
            assert listening(ports) == {p: set() for p in ports}  # nothing listens where the stack did
            after = stack_command(tmp_path, "status", "--json", "--timeout", "0.5")
            assert after.returncode == 0, after.stderr
            gone = json.loads(after.stdout)
            assert gone["processes"] == [] and gone["alive"] == [] and gone["router_error"]
        finally:
            stop_all(cfg.root, 30.0)  # whatever a failed test left running


def test_status_without_a_stack_says_so(tmp_path: Path) -> None:
    with ReservedPort() as nobody:  # bound, never listening: no router there
        env = {**os.environ, "NAVI_ZENOH_CONNECT": f"tcp/127.0.0.1:{nobody.port}"}
        out = subprocess.run(
            [sys.executable, "-m", "navi", "stack", "status", "--json", "--timeout", "0.5"],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert out.returncode == 0, out.stderr
    status = json.loads(out.stdout)
    assert status["processes"] == [] and status["alive"] == [] and status["router_error"]
    assert status["learner"] is None
