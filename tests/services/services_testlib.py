"""Helpers for the service tests (imported through conftest.py): reserved ports, the `navi` command,
managed service processes, waiting on a condition."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import httpx

NAVI = (sys.executable, "-m", "navi")
HOLDPOINT = Path(__file__).with_name("holdpoint.py")


class ReservedPort:
    """A loopback port the OS picked, held by a bound socket (SO_REUSEADDR, never listening) until
    `close()`: for a server whose port must be known before it starts or kept across its restarts.

    The server binds the same port with SO_REUSEADDR (Zenoh, uvicorn, prometheus_client, Go servers do)
    while this socket holds it; the kernel hands the port to no other bind(0) or outgoing connection in
    the meantime. A server that can report its own port binds port 0 instead (see `Service.logged`)."""

    def __init__(self) -> None:
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._socket.bind(("127.0.0.1", 0))
        self.port = int(self._socket.getsockname()[1])

    def close(self) -> None:
        self._socket.close()

    def __enter__(self) -> ReservedPort:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.1) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")


@contextlib.contextmanager
def loopback_router() -> Iterator[str]:
    """A Zenoh router in this process on a loopback port the OS picks; yields its endpoint as bound
    (read back from the router's admin space)."""
    from navi_mesh.session import SessionConfig, open_new_session, router_locators

    router = open_new_session(SessionConfig(mode="router", connect=(), listen=("tcp/127.0.0.1:0",)))
    try:
        (endpoint,) = router_locators(router)
        yield endpoint
    finally:
        router.close()


def client_session(endpoint: str) -> Any:
    """A Zenoh client session to `endpoint` (fails after a minute without the router)."""
    from navi_mesh.session import SessionConfig, open_new_session

    return open_new_session(SessionConfig(connect=(endpoint,), connect_timeout_s=60.0))


def connected_routers(sess: Any) -> int:
    """How many routers the Zenoh session `sess` is connected to right now."""
    return len(list(sess.info.routers_zid()))


def matched(sess: Any, key: str, queryable: bool = False, timeout_s: float = 60.0) -> None:
    """Wait until a put (or, `queryable`, a query) from `sess` on `key` reaches a subscriber (queryable)
    declared elsewhere: Zenoh's matching status, which turns true once the router has told `sess` of
    the remote declaration. A put sent before that may reach nobody."""
    probe = sess.declare_querier(key) if queryable else sess.declare_publisher(key)
    try:
        wait_for(lambda: bool(probe.matching_status.matching), timeout_s, f"a match on {key}", poll_s=0.01)
    finally:
        probe.undeclare()


@dataclass(frozen=True)
class HoldPoint:
    """A point where a service started through holdpoint.py stops, one thread waiting to be killed: the
    audit `event` whose path matches `path`, after `skip` such events. The first process to get there
    writes its pid to `marker`."""

    event: str
    path: str
    marker: Path
    skip: int = 0

    def env(self) -> dict[str, str]:
        return {
            "HOLDPOINT_EVENT": self.event,
            "HOLDPOINT_PATH": self.path,
            "HOLDPOINT_MARKER": str(self.marker),
            "HOLDPOINT_SKIP": str(self.skip),
        }

    def reached(self, timeout_s: float = 300.0) -> int:
        """Wait until a process stopped at the point; its pid."""

        def pid() -> str:
            return self.marker.read_text() if self.marker.is_file() else ""

        wait_for(lambda: pid().isdigit(), timeout_s, f"a process to stop at {self.event} {self.path}")
        return int(pid())


class Service:
    """A `navi serve ...` child process with its log file (through holdpoint.py with a `hold`)."""

    def __init__(
        self, name: str, args: list[str], cwd: Path, env: dict[str, str], hold: HoldPoint | None = None
    ) -> None:
        self.name = name
        self.log = cwd / f"{name}.log"
        self._log = self.log.open("ab")
        launcher = NAVI if hold is None else (sys.executable, str(HOLDPOINT))
        self.proc = subprocess.Popen(
            [*launcher, *args],
            cwd=cwd,
            env=env if hold is None else {**env, **hold.env()},
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 20.0) -> int:
        if self.alive():
            os.kill(self.proc.pid, sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self._log.close()
        return int(self.proc.returncode)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def logged(self, pattern: str, timeout_s: float = 120.0) -> re.Match[str]:
        """The first match of `pattern` in the log, waiting for it while the process runs (a port the
        service bound and logged, a state it reached)."""
        found: list[re.Match[str]] = []

        def seen() -> bool:
            match = re.search(pattern, self.text())
            if match is None and not self.alive():
                raise AssertionError(f"{self.name} exited before logging {pattern!r}:\n{self.text()[-3000:]}")
            found[:] = [match] if match else []
            return match is not None

        wait_for(seen, timeout_s, f"{self.name} to log {pattern!r}")
        return found[0]

    def metrics_port(self, service: str, timeout_s: float = 120.0) -> int:
        """The port of GET /metrics that a service started with `--metrics-port 0` bound and logged."""
        return int(
            self.logged(rf"GET /metrics of {service} on http://127\.0\.0\.1:(\d+)/metrics", timeout_s)[1]
        )


class Services:
    """Starts services in one working folder with one environment; stops them all at the end."""

    def __init__(self, cwd: Path, env: dict[str, str]) -> None:
        self.cwd, self.env = cwd, env
        self.started: list[Service] = []
        self.sessions: list[Any] = []
        self.ports: list[ReservedPort] = []

    def reserve_port(self) -> int:
        """A port reserved until the services stop (for a server that cannot report the port it bound)."""
        self.ports.append(ReservedPort())
        return self.ports[-1].port

    def session(self) -> Any:
        """A Zenoh client session of the test, closed before the services stop."""
        from navi_mesh.session import SessionConfig, open_new_session

        sess = open_new_session(
            SessionConfig(connect=(self.env["NAVI_ZENOH_CONNECT"],), connect_timeout_s=10.0)
        )
        self.sessions.append(sess)
        return sess

    def start(self, name: str, *args: str, hold: HoldPoint | None = None) -> Service:
        svc = Service(name, list(args), self.cwd, self.env, hold)
        self.started.append(svc)
        return svc

    def stop_all(self) -> None:
        for sess in self.sessions:
            sess.close()
        for svc in reversed(self.started):
            svc.stop(signal.SIGKILL if svc.name.startswith("router") else signal.SIGTERM, 10.0)
        for port in self.ports:
            port.close()


def services_fixture(tmp_path: Path) -> Iterator[Services]:
    """Services in `tmp_path`; the router port is reserved for the whole test, so a router restarted
    under a test (a router outage) listens where its clients reconnect."""
    router_port = ReservedPort()
    port = router_port.port
    env: dict[str, str] = {
        **os.environ,
        "NAVI_ZENOH_CONNECT": f"tcp/127.0.0.1:{port}",
        "NAVI_ZENOH_LISTEN": f"tcp/127.0.0.1:{port}",
        "NAVI_ARTIFACTS_DIR": str(tmp_path / "artifacts"),
        "NAVI_API_TOKEN": "",
        "PYTHONUNBUFFERED": "1",
        "OMP_NUM_THREADS": "1",
    }
    svc = Services(tmp_path, env)
    try:
        yield svc
    finally:
        svc.stop_all()
        router_port.close()


def small_cpu_stack(folder: Path, mp: Any, ports: contextlib.ExitStack) -> Any:
    """A `navi stack` config for the tests: every port reserved on loopback (held by `ports` until it
    closes), no corpus yet (2 procedural scenes at 64^3 get built), 32x8 rays, 2 learner actors and 1
    env actor on the CPU. `mp` (a pytest MonkeyPatch) moves into `folder` and sets the environment the
    services read."""
    from navi.stack import StackConfig

    def reserved() -> int:
        return ports.enter_context(ReservedPort()).port

    mp.chdir(folder)
    for name, value in {
        "NAVI_API_TOKEN": "",
        "NAVI_ARTIFACTS_DIR": str(folder / "artifacts"),
        "NAVI_AZIMUTH_BINS": "32",
        "NAVI_ELEVATION_BINS": "8",
        "OMP_NUM_THREADS": "1",
    }.items():
        mp.setenv(name, value)
    return StackConfig(
        root=folder / "artifacts" / "stack",  # where `navi stack status` looks from `folder`
        router_port=reserved(),
        api_port=reserved(),
        auditor_port=reserved(),
        compiler_metrics_port=reserved(),
        env_metrics_port=reserved(),
        corpus=folder / "artifacts" / "corpus" / "default",
        corpus_scenes=2,
        corpus_resolution=64,
        actors=2,
        env_actors=1,
        device="cpu",
        auditor=True,
        navi=NAVI,
    )


def learner_health(port: int) -> dict[str, Any] | None:
    """The learner's /healthz body, or None while it does not answer 200."""
    try:
        reply = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0)
        return reply.json() if reply.status_code == 200 else None
    except (httpx.HTTPError, ValueError):
        return None
