"""docker-compose.yml and deploy/ checked structurally (no Docker engine here): every command is a
real `navi` sub-command with valid options, every referenced file exists, ports and names agree."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import typer
import yaml

from navi_mesh import metrics

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES: dict[str, Any] = COMPOSE["services"]
NAVI_SERVICES = ("learner", "env", "compiler", "auditor")


def navi_click() -> Any:
    """The root command as typer builds it (a group: `.commands` maps names to commands)."""
    from navi import cli as root

    return typer.main.get_command(root.build_app())


def env_file() -> dict[str, str]:
    lines = (ROOT / "deploy" / "navi.env").read_text().splitlines()
    pairs = [line.split("=", 1) for line in lines if line.strip() and not line.startswith("#")]
    return {k.strip(): v.strip() for k, v in pairs}


def option_value(command: list[str], name: str) -> str:
    return command[command.index(name) + 1]


def endpoint_port(endpoint: str) -> int:
    match = re.search(r":(\d+)$", endpoint)
    assert match, endpoint
    return int(match.group(1))


@pytest.mark.parametrize("name", NAVI_SERVICES)
def test_every_command_is_a_real_navi_subcommand(name: str) -> None:
    command = SERVICES[name]["command"]
    assert command[:2] == ["navi", "serve"], command
    group = navi_click()
    args = command[1:]
    path = []
    while hasattr(group, "commands") and args and args[0] in group.commands:
        path.append(args[0])
        group = group.commands[args.pop(0)]
    assert path == ["serve", name] and not hasattr(group, "commands")
    ctx = group.make_context(
        " ".join(["navi", *path]), list(args)
    )  # raises on an unknown option or bad value
    assert ctx.params


def test_referenced_files_exist() -> None:
    for name, svc in SERVICES.items():
        build = svc.get("build")
        if build:
            dockerfile = ROOT / build["context"] / build["dockerfile"]
            assert dockerfile.is_file(), f"{name}: {dockerfile}"
            for line in dockerfile.read_text().splitlines():
                if line.startswith("COPY "):
                    for src in line.split()[1:-1]:
                        assert (ROOT / src).exists(), f"{dockerfile.name} copies missing {src}"
        for entry in svc.get("env_file", []):
            if entry.get("required", True):
                assert (ROOT / entry["path"]).is_file(), f"{name}: env file {entry['path']}"
        for volume in svc.get("volumes", []):
            host = volume.split(":")[0]
            if host.startswith("./deploy"):
                assert (ROOT / host).exists(), f"{name}: mounts missing {host}"
            else:
                assert host.startswith("./artifacts"), f"{name}: unexpected mount {host}"


def test_token_and_settings_come_from_env_files() -> None:
    for name in NAVI_SERVICES:
        paths = [e["path"] for e in SERVICES[name]["env_file"]]
        assert paths == ["deploy/navi.env", ".env"], name
        assert "NAVI_API_TOKEN" not in json.dumps(SERVICES[name].get("environment", {}))
    assert ".env" in (ROOT / ".gitignore").read_text().split()


def test_ports_agree_with_the_config() -> None:
    settings = env_file()
    router_json = (ROOT / "deploy" / "zenoh" / "router.json5").read_text()
    listen = re.findall(r'"tcp/\[::\]:(\d+)"', router_json)
    connect = settings["NAVI_ZENOH_CONNECT"]
    assert connect == f"tcp/router:{listen[0]}"
    assert f"127.0.0.1:{listen[0]}:{listen[0]}" in SERVICES["router"]["ports"]
    rest_port = re.search(r"http_port:\s*(\d+)", router_json)
    assert rest_port and f"localhost:{rest_port.group(1)}/" in " ".join(
        SERVICES["router"]["healthcheck"]["test"]
    )

    api_port = settings["NAVI_API_PORT"]
    learner = SERVICES["learner"]["command"]
    assert (
        option_value(learner, "--port") == api_port
        and f"127.0.0.1:{api_port}:{api_port}" in SERVICES["learner"]["ports"]
    )
    metrics_port = settings["NAVI_METRICS_PORT"]
    for name in ("env", "compiler"):
        assert option_value(SERVICES[name]["command"], "--metrics-port") == metrics_port
    auditor_port = settings["NAVI_AUDITOR_PORT"]
    assert option_value(SERVICES["auditor"]["command"], "--port") == auditor_port

    expected = {"learner": api_port, "env": metrics_port, "compiler": metrics_port, "auditor": auditor_port}
    for name, port in expected.items():
        assert f"localhost:{port}/" in " ".join(SERVICES[name]["healthcheck"]["test"]), name

    prom = yaml.safe_load((ROOT / "deploy" / "prometheus" / "prometheus.yml").read_text())
    targets = {t for job in prom["scrape_configs"] for sc in job["static_configs"] for t in sc["targets"]}
    assert {f"{name}:{port}" for name, port in expected.items()} <= targets
    for target in targets - {"localhost:9090"}:
        assert target.split(":")[0] in SERVICES
    assert "127.0.0.1:9090:9090" in SERVICES["prometheus"]["ports"]


def test_published_ports_are_loopback_only_and_services_listen_inside_the_network() -> None:
    """The host sees every published port on 127.0.0.1 only; inside the compose network each navi
    service binds all interfaces (so Prometheus and the other services reach it by name)."""
    published = [(name, port) for name, svc in SERVICES.items() for port in svc.get("ports", [])]
    assert {name for name, _ in published} == {"router", "learner", "auditor", "prometheus", "grafana"}
    for name, port in published:
        assert str(port).startswith("127.0.0.1:"), (name, port)
    assert option_value(SERVICES["learner"]["command"], "--host") == "0.0.0.0"
    assert option_value(SERVICES["auditor"]["command"], "--host") == "0.0.0.0"
    for name in ("env", "compiler"):
        assert option_value(SERVICES[name]["command"], "--metrics-host") == "0.0.0.0", name


def test_local_serve_commands_default_to_loopback() -> None:
    """Without the compose file's options every `navi serve` command binds 127.0.0.1."""
    from navi_contracts.settings import NaviSettings

    serve = navi_click().commands["serve"]
    defaults = {
        (name, p.name): p.default
        for name, cmd in serve.commands.items()
        for p in cmd.params
        if p.name in ("host", "metrics_host")
    }
    assert defaults == {
        ("learner", "host"): "127.0.0.1",
        ("auditor", "host"): "127.0.0.1",
        ("env", "metrics_host"): "127.0.0.1",
        ("compiler", "metrics_host"): "127.0.0.1",
    }
    assert NaviSettings.model_fields["zenoh_listen"].default == "tcp/127.0.0.1:7447"


def test_every_service_has_a_health_check_and_the_learner_a_gpu() -> None:
    for name, svc in SERVICES.items():
        assert "healthcheck" in svc, name
    for name in ("learner", "env", "compiler"):
        devices = SERVICES[name]["deploy"]["resources"]["reservations"]["devices"]
        assert devices[0]["capabilities"] == ["gpu"]
    assert option_value(SERVICES["compiler"]["command"], "--device") == "auto"  # the GPU engine on a GPU
    assert SERVICES["router"]["image"].startswith("eclipse/zenoh:")
    cuda = (ROOT / "deploy" / "cuda.Dockerfile").read_text()
    slim = (ROOT / "deploy" / "slim.Dockerfile").read_text()
    assert re.search(r"^FROM nvidia/cuda:\S+-runtime-", cuda, re.M)
    assert re.search(r"^FROM python:3\.11-slim", slim, re.M)
    assert (
        SERVICES["learner"]["build"]["dockerfile"]
        == SERVICES["env"]["build"]["dockerfile"]
        == SERVICES["compiler"]["build"]["dockerfile"]
        == "deploy/cuda.Dockerfile"
    )
    assert SERVICES["auditor"]["build"]["dockerfile"] == "deploy/slim.Dockerfile"


def test_grafana_provisioning_and_dashboard_use_real_metrics() -> None:
    grafana = SERVICES["grafana"]["volumes"]
    mounts = dict(v.split(":")[:2] for v in grafana)
    provider = yaml.safe_load((ROOT / "deploy/grafana/provisioning/dashboards/navi.yml").read_text())
    assert provider["providers"][0]["options"]["path"] == mounts["./deploy/grafana/dashboards"]
    source = yaml.safe_load((ROOT / "deploy/grafana/provisioning/datasources/prometheus.yml").read_text())
    assert source["datasources"][0]["url"] == "http://prometheus:9090"

    dashboard = json.loads((ROOT / "deploy/grafana/dashboards/navi.json").read_text())
    exprs = " ".join(t["expr"] for p in dashboard["panels"] for t in p["targets"])
    suffixes = {"counter": ("_total",), "histogram": ("_bucket", "_sum", "_count"), "gauge": ("",)}
    known = {f.name + s for f in metrics.REGISTRY.collect() for s in suffixes.get(f.type, ("",))}
    used = set(re.findall(r"\bnavi_[a-z_]+", exprs))
    assert used and used <= known, used - known
    for needed in (
        "navi_steps_per_second",
        "navi_reward_ema",
        "navi_loss",
        "navi_gpu_memory_bytes",
        "navi_compile_jobs_total",
        "navi_dropped_messages_total",
        "navi_corpus_scenes_ready",
    ):
        assert needed in used, needed
