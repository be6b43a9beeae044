"""`navi stack up|down|status`: the compose stack as local processes, with the same commands and config.

Each service is `python -m navi serve <name> ...` started in its own session (process group), its
output in artifacts/stack/<name>.log and a pid file artifacts/stack/<name>.pid (JSON: pid, argv,
start time). All five start at once, bound to `host` (127.0.0.1 unless told otherwise); `up` returns
when each answers its health check (router: a Zenoh session opens; compiler, env: GET /metrics;
learner: GET /healthz; auditor: GET /healthz). A missing corpus does not hold anything up: the
learner builds it over compile jobs in the background (progress in its /healthz and in
`navi stack status`), the env waits for it, and training starts when it is ready. `down` sends
SIGTERM in reverse start order and SIGKILL to what is still alive after the grace period. `status`
joins the pid files with the live liveliness tokens and the learner's /healthz.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

STACK_DIR = Path("artifacts/stack")


def navi_argv() -> tuple[str, ...]:
    """How to run the `navi` command from this interpreter."""
    return (sys.executable, "-m", "navi")


TOKEN_FILE = "api_token"
CONFIG_FILE = "stack.json"
"""Ports and host of the running stack (written by `up`, read by `status`)."""
ORDER = ("router", "compiler", "env", "learner", "auditor")


@dataclass(frozen=True)
class StackConfig:
    """The local stack."""

    root: Path = STACK_DIR
    """Pid files, logs and the generated token."""
    host: str = "127.0.0.1"
    """Interface every service binds (router, control plane, dashboard, /metrics); 0.0.0.0 for all."""
    router_port: int = 7447
    """Zenoh router port."""
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
    corpus_scenes: int = 16
    """Scenes of the default corpus when it is built."""
    corpus_resolution: int = 512
    """Resolution of the default corpus when it is built."""
    compiler_workers: int = 1
    """Compile worker threads (each takes one job at a time)."""
    actors: int = 4
    """Learner actors (per rank with nproc > 1)."""
    nproc: int = 1
    """Learner data-parallel ranks, one per GPU (`navi serve learner --nproc`)."""
    env_actors: int = 2
    """Env-service actors (for an external brain)."""
    device: str = "auto"
    """Torch device of the learner, the env and the compiler (auto: the GPU engine on a CUDA host)."""
    total_steps: int = 10_000_000
    """Learner training budget."""
    auditor: bool = True
    """Start the auditor dashboard when navi_auditor is installed."""
    navi: tuple[str, ...] = field(default_factory=navi_argv)
    """The `navi` command line prefix the services run with (default: this interpreter's `-m navi`)."""
    learner_args: tuple[str, ...] = ()
    """More options of the learner's command (e.g. `--checkpoint-every N --resume-latest`)."""
    compiler_args: tuple[str, ...] = ()
    """More options of the compiler's command (e.g. `--max-source-mb N`)."""
    cwd: Path | None = None
    """Working folder of the services (their artifacts/ folder lies under it); None: this process's."""


class StackError(RuntimeError):
    """The stack cannot be started (already running, no corpus, ...)."""


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


def service_specs(cfg: StackConfig, with_auditor: bool) -> list[ServiceSpec]:
    """The processes of the stack in start order: the same `navi serve` commands compose runs."""
    navi = (*cfg.navi, "serve")
    specs = [
        ServiceSpec("router", (*navi, "router", "--listen", f"tcp/{cfg.host}:{cfg.router_port}")),
        ServiceSpec(
            "compiler",
            (
                *navi,
                "compiler",
                "--workers",
                str(cfg.compiler_workers),
                "--device",
                cfg.device,
                "--metrics-port",
                str(cfg.compiler_metrics_port),
                "--metrics-host",
                cfg.host,
                *cfg.compiler_args,
            ),
        ),
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
                "--metrics-host",
                cfg.host,
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
                "--corpus-scenes",
                str(cfg.corpus_scenes),
                "--corpus-resolution",
                str(cfg.corpus_resolution),
                "--actors",
                str(cfg.actors),
                "--device",
                cfg.device,
                "--total-steps",
                str(cfg.total_steps),
                "--host",
                cfg.host,
                "--port",
                str(cfg.api_port),
                *(("--nproc", str(cfg.nproc)) if cfg.nproc > 1 else ()),
                *cfg.learner_args,
            ),
        ),
    ]
    if with_auditor:
        specs.append(
            ServiceSpec("auditor", (*navi, "auditor", "--host", cfg.host, "--port", str(cfg.auditor_port)))
        )
    return specs


def probe_host(host: str) -> str:
    """Where to reach a service bound to `host` from this machine."""
    return "127.0.0.1" if host in ("0.0.0.0", "::", "") else host


def health_urls(cfg: StackConfig) -> dict[str, str]:
    """The HTTP health check of each service that has one (the router's is a Zenoh session)."""
    h = probe_host(cfg.host)
    return {
        "compiler": f"http://{h}:{cfg.compiler_metrics_port}/metrics",
        "env": f"http://{h}:{cfg.env_metrics_port}/metrics",
        "learner": f"http://{h}:{cfg.api_port}/healthz",
        "auditor": f"http://{h}:{cfg.auditor_port}/healthz",
    }


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

    token = NaviSettings().api_token.get_secret_value()
    if token:
        return token, False
    token = secrets.token_urlsafe(24)
    path = root / TOKEN_FILE
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token, True


def start(spec: ServiceSpec, root: Path, env: dict[str, str], cwd: Path | None = None) -> ProcessState:
    """Start one service detached (own session) in `cwd`, logging to root/<name>.log; write its pid file."""
    log_path = root / f"{spec.name}.log"
    with log_path.open("ab") as log_file:
        proc = subprocess.Popen(
            spec.argv,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=cwd,
            start_new_session=True,
        )
    started = time.time()
    pid_file(root, spec.name).write_text(
        json.dumps({"pid": proc.pid, "argv": list(spec.argv), "started_at": started})
    )
    return ProcessState(spec.name, proc.pid, True, started, str(log_path))


def stop_all(root: Path, grace_s: float = 20.0) -> list[ProcessState]:
    """SIGTERM every running service (reverse start order), SIGKILL after grace_s to the service's process
    group (its own session: a multi-GPU learner's torchrun and ranks go with it); remove pid files."""
    states = read_states(root)
    for st in reversed(states):
        if st.running:
            os.kill(st.pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(is_running(st.pid) for st in states):
        time.sleep(0.1)
    for st in states:
        if is_running(st.pid):
            try:
                os.killpg(st.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                os.kill(st.pid, signal.SIGKILL)
    for st in states:
        pid_file(root, st.name).unlink(missing_ok=True)
    return [ProcessState(st.name, st.pid, is_running(st.pid), st.started_at, st.log) for st in states]


def has_auditor() -> bool:
    """navi_auditor's dashboard is installed."""
    import importlib.util

    return (
        importlib.util.find_spec("navi_auditor") is not None
        and importlib.util.find_spec("navi_auditor.server") is not None
    )


def wait_for_tokens(router_port: int, names: list[str], wait_s: float) -> list[str]:
    """Wait until every named service holds a liveliness token; returns the names still missing."""
    from navi_mesh.liveliness import live_tokens
    from navi_mesh.session import MeshError, SessionConfig, open_new_session

    deadline = time.monotonic() + wait_s
    cfg = SessionConfig(
        connect=(f"tcp/127.0.0.1:{router_port}",), connect_timeout_s=max(1.0, min(10.0, wait_s))
    )
    try:
        sess = open_new_session(cfg)
    except MeshError:
        return list(names)
    try:
        missing = list(names)
        while missing and time.monotonic() < deadline:
            alive = {t.service for t in live_tokens(sess, timeout_s=1.0)}
            missing = [n for n in names if n not in alive]
            if missing:
                time.sleep(0.5)
        return missing
    finally:
        sess.close()


def http_ok(url: str, timeout_s: float = 1.0) -> bool:
    """GET url answers 200."""
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as r:
            return int(r.status) == 200
    except (urllib.error.URLError, OSError, ValueError):
        return False


def router_ok(host: str, port: int, timeout_s: float = 1.0) -> bool:
    """A Zenoh client session to the router opens within timeout_s."""
    from navi_mesh.session import MeshError, SessionConfig, open_new_session

    try:
        sess = open_new_session(SessionConfig(connect=(f"tcp/{host}:{port}",), connect_timeout_s=timeout_s))
    except MeshError:
        return False
    sess.close()
    return True


def wait_for_health(cfg: StackConfig, names: list[str], t0: float, wait_s: float) -> dict[str, float | None]:
    """Seconds from t0 (time.monotonic()) until each named service passed its health check; None for
    those that did not within wait_s."""
    urls = health_urls(cfg)
    healthy: dict[str, float | None] = dict.fromkeys(names)
    deadline = t0 + wait_s
    while any(v is None for v in healthy.values()) and time.monotonic() < deadline:
        for name in [n for n, v in healthy.items() if v is None]:
            ok = router_ok(probe_host(cfg.host), cfg.router_port) if name == "router" else http_ok(urls[name])
            if ok:
                healthy[name] = time.monotonic() - t0
        if any(v is None for v in healthy.values()):
            time.sleep(0.2)
    return healthy


@dataclass(frozen=True)
class StackStarted:
    """What `up` started and how long each service took to pass its health check."""

    states: list[ProcessState]
    healthy_after_s: dict[str, float | None]
    """Seconds from the start of `up` to each service's first good health check (None: not within the wait)."""


def learner_health(root: Path, timeout_s: float = 1.0) -> dict[str, object] | None:
    """The running stack's learner /healthz as JSON (phase, corpus progress), None when unreachable."""
    import urllib.error
    import urllib.request

    try:
        saved = json.loads((root / CONFIG_FILE).read_text())
        url = f"http://{probe_host(saved['host'])}:{int(saved['api_port'])}/healthz"
        with urllib.request.urlopen(url, timeout=timeout_s) as r:
            body: dict[str, object] = json.loads(r.read())
            return body
    except (OSError, ValueError, KeyError, urllib.error.URLError):
        return None


def up(
    cfg: StackConfig, wait_s: float, progress: Callable[[str], None], announce: Callable[[str], None]
) -> StackStarted:
    """Start the stack: a token when NAVI_API_TOKEN is unset (announced once), then every service at
    once; waits up to wait_s for their health checks. A missing corpus is built in the background."""
    t0 = time.monotonic()
    cfg.root.mkdir(parents=True, exist_ok=True)
    if any(s.running for s in read_states(cfg.root)):
        raise StackError(f"the stack is already running (see `navi stack status`; pid files in {cfg.root})")
    token, generated = api_token(cfg.root)
    if generated:
        announce(f"NAVI_API_TOKEN was unset; generated one for this stack (also in {cfg.root / TOKEN_FILE}):")
        announce(f"  {token}")
    env = {
        **os.environ,
        "NAVI_API_TOKEN": token,
        "NAVI_ZENOH_CONNECT": f"tcp/{probe_host(cfg.host)}:{cfg.router_port}",
    }
    specs = service_specs(cfg, cfg.auditor and has_auditor())
    (cfg.root / CONFIG_FILE).write_text(
        json.dumps({"host": cfg.host, "api_port": cfg.api_port, "router_port": cfg.router_port})
    )
    states = []
    for spec in specs:
        state = start(spec, cfg.root, env, cfg.cwd)
        states.append(state)
        progress(f"started {state.name:<9} pid {state.pid}  log {state.log}")
    healthy = wait_for_health(cfg, [s.name for s in specs], t0, wait_s)
    for name, after in healthy.items():
        if after is None:
            progress(f"warning: {name} did not pass its health check within {wait_s:g} s (see {cfg.root})")
        else:
            progress(f"{name:<9} healthy after {after:.1f} s")
    if not (cfg.corpus / "manifest.json").is_file():
        progress(
            f"the corpus {cfg.corpus} is being built in the background over compile jobs; training starts "
            f"when it is ready (progress: `navi stack status`, GET /healthz on port {cfg.api_port})"
        )
    return StackStarted(states, healthy)
