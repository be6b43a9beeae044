"""A running stack as an operator sees it, on loopback: each service's /metrics holds the mesh families and
the ones that service owns (no learner gauge at 0 on a compiler's page), and a real Prometheus scraping
the stack answers every Grafana panel's query with the series it is meant to, event-driven panels after
the test causes the event (a compile job, a promotion, a dropped and a malformed message)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import threading
import urllib.parse
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import torch
from prometheus_client.parser import text_string_to_metric_families
from services_testlib import NAVI, ReservedPort, small_cpu_stack, wait_for

from navi.stack import StackConfig, has_auditor, stop_all, up
from navi_contracts.codec import decode_any, encode
from navi_contracts.models import StepRequest, TelemetryEvent
from navi_contracts.topics import STEP, TELEMETRY
from navi_learner.config import TrainConfig
from navi_learner.serving.checkpoint import CheckpointMeta, save_checkpoint
from navi_mesh import metrics
from navi_mesh.session import SessionConfig, open_new_session

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
PANELS = json.loads((ROOT / "deploy/grafana/dashboards/navi.json").read_text())["panels"]


@dataclass
class RunningStack:
    cfg: StackConfig
    folder: Path
    services: list[str]
    training_rows: list[str] = field(default_factory=list)  # keys of the actor.training.* events heard
    session: Any = None

    def metrics_url(self, service: str) -> str:
        port = {
            "learner": self.cfg.api_port,
            "compiler": self.cfg.compiler_metrics_port,
            "env": self.cfg.env_metrics_port,
            "auditor": self.cfg.auditor_port,
        }[service]
        return f"http://127.0.0.1:{port}/metrics"


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningStack]:
    """A CPU stack from no corpus (2 procedural scenes at 64^3, 32x8 rays), a telemetry listener on it."""
    folder = tmp_path_factory.mktemp("stack")
    with pytest.MonkeyPatch.context() as mp, contextlib.ExitStack() as reserved:
        cfg = small_cpu_stack(folder, mp, reserved)
        services = ["compiler", "env", "learner", *(["auditor"] if has_auditor() else [])]
        try:
            started = up(cfg, 600.0, lambda line: None, lambda line: None)
            assert all(after is not None for after in started.healthy_after_s.values()), (
                started.healthy_after_s
            )
            running = RunningStack(cfg, folder, services)
            running.session = open_new_session(
                SessionConfig(connect=(f"tcp/127.0.0.1:{cfg.router_port}",), connect_timeout_s=60.0)
            )

            def on_telemetry(sample: Any) -> None:
                try:
                    event = decode_any(bytes(sample.payload))
                except ValueError:
                    return  # the test's own malformed message
                if isinstance(event, TelemetryEvent) and event.key.startswith("actor.training."):
                    running.training_rows.append(event.key)

            subscriber = running.session.declare_subscriber(TELEMETRY.key, on_telemetry)
            yield running
            subscriber.undeclare()
            running.session.close()
        finally:
            stop_all(cfg.root, 30.0)


def scrape_families(url: str) -> dict[str, list[dict[str, str]]]:
    """navi_* family name -> the label sets of its samples."""
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    return {
        f.name: [s.labels for s in f.samples]
        for f in text_string_to_metric_families(text)
        if f.name.startswith("navi_")
    }


def families(collectors: tuple[object, ...]) -> set[str]:
    return {f.name for c in collectors for f in c.describe()}  # type: ignore[attr-defined]


def panel_queries() -> list[tuple[str, str, tuple[str, ...]]]:
    """(panel title, PromQL, the labels its `by (...)` groups on) for every target of the dashboard."""
    out = []
    for panel in PANELS:
        for target in panel.get("targets", []):
            by = re.search(r"by \(([^)]*)\)", target["expr"])
            labels = tuple(x.strip() for x in by.group(1).split(",")) if by else ()
            out.append((panel["title"], target["expr"], tuple(x for x in labels if x != "le")))
    return out


def test_each_service_exports_its_own_metrics_with_the_dashboards_labels(stack: RunningStack) -> None:
    wait_for(lambda: bool(stack.training_rows), 600.0, "the first training row")
    scraped = {service: scrape_families(stack.metrics_url(service)) for service in stack.services}
    for service, found in scraped.items():
        assert set(found) == families(metrics.MESH) | families(metrics.OWNERS[service]), service
    # Where a family has samples, they carry the labels the dashboard groups by.
    for title, expr, labels in panel_queries():
        for name in set(re.findall(r"\bnavi_[a-z_]+?(?=_total\b|_bucket\b|\b)", expr)):
            owners = [s for s in stack.services if name in scraped[s]]
            assert owners, (title, name)
            for service in owners:
                for sample_labels in scraped[service][name]:
                    assert set(labels) <= set(sample_labels), (title, service, name, sample_labels)
    # The learner's gauges come from the learner alone: one series per panel where one is meant.
    assert scraped["learner"]["navi_reward_ema"] and all(
        "navi_reward_ema" not in scraped[s] for s in stack.services if s != "learner"
    )


def prometheus_config(stack: RunningStack) -> str:
    jobs = "".join(
        f"  - job_name: {service}\n    static_configs:\n      - targets: ['{stack.metrics_url(service)[7:-8]}']\n"
        for service in stack.services
    )
    return f"global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\nscrape_configs:\n{jobs}"


def query(port: int, expr: str) -> list[dict[str, Any]]:
    url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
    body = json.loads(urllib.request.urlopen(url, timeout=5).read())
    assert body["status"] == "success", body
    return list(body["data"]["result"])


def cause_the_events(stack: RunningStack) -> None:
    """A compile job, a promotion, a malformed message and dropped requests, as an operator would."""
    from navi_compiler.gmdag import read_gmdag

    env = {**os.environ, "NAVI_ZENOH_CONNECT": f"tcp/127.0.0.1:{stack.cfg.router_port}"}
    scenes = stack.folder / "event-scenes"
    subprocess.run(
        [*NAVI, "scenes", "generate", "--out", str(scenes), "--count", "1"], check=True, timeout=600
    )
    source = next(p for p in sorted(scenes.iterdir()) if p.suffix != ".json")
    compiled = subprocess.run(
        [*NAVI, "compile", str(source), "-o", str(stack.folder / "event.gmdag"), "--resolution", "32", "--remote"],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert compiled.returncode == 0, compiled.stderr
    read_gmdag(stack.folder / "event.gmdag")  # the worker wrote a whole, valid scene

    meta = CheckpointMeta(1, 0, 0.5, 0.0, "gru", "prometheus-test", TrainConfig().to_dict(), [3, 32, 8])
    ckpt = save_checkpoint(stack.folder / "event.pt", {"w": torch.ones(2)}, None, meta)
    token = (stack.cfg.root / "api_token").read_text().strip()
    promoted = httpx.post(
        f"http://127.0.0.1:{stack.cfg.api_port}/models/promote",
        json={"checkpoint": str(ckpt), "alias": "champion"},
        headers={"Authorization": f"Bearer {token}"},
        timeout=60.0,
    )
    assert promoted.status_code == 200, promoted.text

    sess = stack.session
    sess.put(TELEMETRY.key, b"\xc1")  # not msgpack: the auditor drops and counts it
    for _ in range(3):
        sess.get(STEP.key, payload=b"\xc1")  # the env service answers an error and counts it
    one = encode(
        StepRequest(request_id="flood", env_ids=np.zeros(1, np.int32), actions=np.zeros((1, 4), np.float32))
    )
    replies = [sess.get(STEP.key, payload=one, timeout=20.0) for _ in range(400)]  # more than its queue holds
    threading.Thread(target=lambda: [list(r) for r in replies], daemon=True).start()


@pytest.mark.skipif(shutil.which("prometheus") is None, reason="the prometheus binary is not installed "
                    "(apt-get install prometheus; .ci/run installs Debian's package)")  # fmt: skip
def test_every_grafana_panel_returns_its_series_from_a_real_prometheus(stack: RunningStack) -> None:
    wait_for(lambda: bool(stack.training_rows), 600.0, "the first training row")
    reserved = ReservedPort()  # Prometheus binds it (SO_REUSEADDR) while the test holds it
    port = reserved.port
    config = stack.folder / "prometheus.yml"
    config.write_text(prometheus_config(stack))
    check = subprocess.run(["promtool", "check", "config", str(config)], capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    log = (stack.folder / "prometheus.log").open("wb")
    prom = subprocess.Popen(
        ["prometheus", f"--config.file={config}", f"--storage.tsdb.path={stack.folder / 'tsdb'}",
         f"--web.listen-address=127.0.0.1:{port}"],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:

        def ready() -> bool:
            try:
                return httpx.get(f"http://127.0.0.1:{port}/-/ready").status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(ready, 120.0, "prometheus")
        wait_for(
            lambda: len([t for t in query(port, "up") if t["value"][1] == "1"]) == len(stack.services),
            120.0,
            "every target up",
        )

        def scraped_twice() -> bool:
            """Two good scrapes of every target: rate() then sees the events below as increases."""
            counts = query(port, "sum_over_time(up[10m])")
            return len(counts) == len(stack.services) and all(float(c["value"][1]) >= 2 for c in counts)

        wait_for(scraped_twice, 120.0, "two scrapes of every target before the events", poll_s=0.5)
        cause_the_events(stack)
        for title, expr, labels in panel_queries():
            if "gpu_memory" in expr and not torch.cuda.is_available():
                continue  # CUDA memory: no series on a CPU stack, by design
            result: list[dict[str, Any]] = []

            def answered(expr: str = expr) -> bool:
                nonlocal result
                result = [r for r in query(port, expr) if r["value"][1] != "NaN"]
                return bool(result)

            wait_for(answered, 300.0, f"panel {title!r}: {expr}", poll_s=1.0)
            for series in result:
                assert set(labels) <= set(series["metric"]), (title, series)
            if not expr.startswith(("sum", "histogram_quantile")):  # a gauge drawn as is: one service's
                assert len({series["metric"]["job"] for series in result}) == 1, (title, result)
    finally:
        prom.terminate()
        prom.wait(60)
        log.close()
        reserved.close()
