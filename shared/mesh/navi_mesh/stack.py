"""`navi stack up|down|status`: the compose stack as local processes, with the same commands and config.

Each service is `python -m navi serve <name> ...` started in its own session (process group), its
output in artifacts/stack/<name>.log and a pid file artifacts/stack/<name>.pid (JSON: pid, argv,
start time). `down` sends SIGTERM in reverse start order and SIGKILL to what is still alive after
the grace period. `status` joins the pid files with the live liveliness tokens.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

STACK_DIR = Path("artifacts/stack")
TOKEN_FILE = "api_token"
ORDER = ("router", "compiler", "env", "learner", "auditor")


@dataclass(frozen=True)
class StackConfig:
    """The local stack."""

    root: Path = STACK_DIR
    """Pid files, logs and the generated token."""
    router_port: int = 7447
    """Zenoh router port on 127.0.0.1."""
    api_port: int = 8000
    """Learner control plane port."""
    auditor_port: int = 8080
    """Auditor web dashboard port."""
    compiler_metrics_port: int = 9101
    """Compiler /metrics port."""
    env_metrics_port: int = 9102
    """Env /metrics port."""
    corpus: Path = Path("artifacts/corpus/default")
    """Corpus of the learner and the env (the procedural default corpus is built when missing)."""
    actors: int = 4
    """Learner actors."""
    env_actors: int = 2
    """Env-service actors (for an external brain)."""
    device: str = "auto"
    """Torch device of the learner and the env."""
    total_steps: int = 10_000_000
    """Learner training budget."""
    auditor: bool = True
    """Start the auditor dashboard when `navi serve auditor` exists."""


@dataclass(frozen=True)
class ServiceSpec:
    """One process of the stack."""

    name: str
    argv: tuple[str, ...]


@dataclass(frozen=True)
class ProcessState:
    """What a pid file says and whether its process runs."""

    name: str
    pid: int
    running: bool
    started_at: float
    log: str


def navi_argv() -> tuple[str, ...]:
    """How to run the `navi` command from this interpreter."""
    return (sys.executable, "-m", "navi")


def service_specs(cfg: StackConfig, with_auditor: bool) -> list[ServiceSpec]:
    """The processes of the stack in start order: the same `navi serve` commands compose runs."""
    navi = (*navi_argv(), "serve")
    specs = [
        ServiceSpec("router", (*navi, "router", "--listen", f"tcp/127.0.0.1:{cfg.router_port}")),
        ServiceSpec("compiler", (*navi, "compiler", "--metrics-port", str(cfg.compiler_metrics_port))),
        ServiceSpec(
            "env",
            (
                *navi,
                "env",
                "--corpus",
                str(cfg.corpus),
                "--actors",
                str(cfg.env_actors),
                "--device",
                cfg.device,
                "--metrics-port",
                str(cfg.env_metrics_port),
            ),
        ),
        ServiceSpec(
            "learner",
            (
                *navi,
                "learner",
                "--mode",
                "train",
                "--corpus",
                str(cfg.corpus),
                "--actors",
                str(cfg.actors),
                "--device",
                cfg.device,
                "--total-steps",
                str(cfg.total_steps),
                "--port",
                str(cfg.api_port),
            ),
        ),
    ]
    if with_auditor:
        specs.append(ServiceSpec("auditor", (*navi, "auditor", "--port", str(cfg.auditor_port))))
    return specs


def pid_file(root: Path, name: str) -> Path:
    return root / f"{name}.pid"


def is_running(pid: int) -> bool:
    """The process exists, is not a zombie, and runs a `serve` command."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return True
    return stat.rsplit(")", 1)[-1].split()[0] != "Z" and b"serve" in cmdline


def read_states(root: Path) -> list[ProcessState]:
    """Every pid file of the stack, in start order."""
    states = []
    for name in ORDER:
        path = pid_file(root, name)
        if not path.is_file():
            continue
        try:
            raw = json.loads(path.read_text())
            pid = int(raw["pid"])
        except (ValueError, KeyError, TypeError):
            continue
        states.append(
            ProcessState(
                name, pid, is_running(pid), float(raw.get("started_at", 0.0)), str(root / f"{name}.log")
            )
        )
    return states


def api_token(root: Path) -> tuple[str, bool]:
    """NAVI_API_TOKEN when set (or in .env), else a new random token; True when it was generated."""
    from navi_contracts.settings import NaviSettings

    token = NaviSettings().api_token.get_secret_value()  # type: ignore[call-arg]
    if token:
        return token, False
    token = secrets.token_urlsafe(24)
    path = root / TOKEN_FILE
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token, True


def start(spec: ServiceSpec, root: Path, env: dict[str, str]) -> ProcessState:
    """Start one service detached (own session), logging to root/<name>.log; write its pid file."""
    log_path = root / f"{spec.name}.log"
    with log_path.open("ab") as log_file:
        proc = subprocess.Popen(
            spec.argv,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            start_new_session=True,
        )
    started = time.time()
    pid_file(root, spec.name).write_text(
        json.dumps({"pid": proc.pid, "argv": list(spec.argv), "started_at": started})
    )
    return ProcessState(spec.name, proc.pid, True, started, str(log_path))


def stop_all(root: Path, grace_s: float = 20.0) -> list[ProcessState]:
    """SIGTERM every running service (reverse start order), SIGKILL after grace_s; remove pid files."""
    states = read_states(root)
    for st in reversed(states):
        if st.running:
            os.kill(st.pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(is_running(st.pid) for st in states):
        time.sleep(0.1)
    for st in states:
        if is_running(st.pid):
            os.kill(st.pid, signal.SIGKILL)
    for st in states:
        pid_file(root, st.name).unlink(missing_ok=True)
    return [ProcessState(st.name, st.pid, is_running(st.pid), st.started_at, st.log) for st in states]
