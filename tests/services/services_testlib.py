"""Helpers for the service tests (imported through conftest.py): free ports, the `navi` command,
managed service processes."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

NAVI = (sys.executable, "-m", "navi")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.1) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")


class Service:
    """A `navi serve ...` child process with its log file."""

    def __init__(self, name: str, args: list[str], cwd: Path, env: dict[str, str]) -> None:
        self.name = name
        self.log = cwd / f"{name}.log"
        self._log = self.log.open("ab")
        self.proc = subprocess.Popen(
            [*NAVI, *args],
            cwd=cwd,
            env=env,
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


class Services:
    """Starts services in one working folder with one environment; stops them all at the end."""

    def __init__(self, cwd: Path, env: dict[str, str]) -> None:
        self.cwd, self.env = cwd, env
        self.started: list[Service] = []
        self.sessions: list[Any] = []

    def session(self) -> Any:
        """A Zenoh client session of the test, closed before the services stop."""
        from navi_mesh.session import SessionConfig, open_new_session

        sess = open_new_session(
            SessionConfig(connect=(self.env["NAVI_ZENOH_CONNECT"],), connect_timeout_s=10.0)
        )
        self.sessions.append(sess)
        return sess

    def start(self, name: str, *args: str) -> Service:
        svc = Service(name, list(args), self.cwd, self.env)
        self.started.append(svc)
        return svc

    def stop_all(self) -> None:
        for sess in self.sessions:
            sess.close()
        for svc in reversed(self.started):
            svc.stop(signal.SIGKILL if svc.name.startswith("router") else signal.SIGTERM, 10.0)


def services_fixture(tmp_path: Path) -> Iterator[Services]:
    port = free_port()
    env = {
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


def small_cpu_stack(folder: Path, mp: Any) -> Any:
    """A `navi stack` config for the tests: every port free on loopback, no corpus yet (2 procedural
    scenes at 64^3 get built), 32x8 rays, 2 learner actors and 1 env actor on the CPU. `mp` (a pytest
    MonkeyPatch) moves into `folder` and sets the environment the services read."""
    from navi.stack import StackConfig

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
        router_port=free_port(),
        api_port=free_port(),
        auditor_port=free_port(),
        compiler_metrics_port=free_port(),
        env_metrics_port=free_port(),
        corpus=folder / "artifacts" / "corpus" / "default",
        corpus_scenes=2,
        corpus_resolution=64,
        actors=2,
        env_actors=1,
        device="cpu",
        auditor=True,
        navi=NAVI,
    )
