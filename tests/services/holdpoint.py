"""`python holdpoint.py ARGS...` runs `navi ARGS...` with one point where a thread stops and waits to be
killed: a test's `kill -9` then lands inside a job or a write, however fast or slow the machine.

HOLDPOINT_EVENT names a Python audit event (`open`, `os.rename`, `tempfile.mkstemp`, ...) and
HOLDPOINT_PATH a regular expression its first argument (a path) must match; HOLDPOINT_SKIP matching
events pass first (default 0). The first process to reach the point creates HOLDPOINT_MARKER (exclusively,
holding its pid) and its thread waits there for good; a process that finds the marker made already goes
on as usual, so of several workers exactly one stops. Nothing else in the process changes.
"""

from __future__ import annotations

import os
import re
import runpy
import sys
import threading
from typing import Any


def install(event: str, path: str, marker: str, skip: int = 0) -> None:
    pattern = re.compile(path)
    passed = [0]
    lock = threading.Lock()

    def hook(name: str, args: tuple[Any, ...]) -> None:
        if name != event or not args or not pattern.search(str(args[0])):
            return
        with lock:
            passed[0] += 1
            if passed[0] <= skip:
                return
        try:
            fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        threading.Event().wait()  # until the process is killed

    sys.addaudithook(hook)


if __name__ == "__main__":
    env = os.environ
    install(
        env["HOLDPOINT_EVENT"],
        env["HOLDPOINT_PATH"],
        env["HOLDPOINT_MARKER"],
        int(env.get("HOLDPOINT_SKIP", "0")),
    )
    sys.argv = ["navi", *sys.argv[1:]]
    runpy.run_module("navi", run_name="__main__", alter_sys=True)
