"""Liveliness tokens: `navi/alive/<service>/<instance id>` while a service's session is up.

A token disappears when its process exits or loses the router, and comes back when the session
reconnects, so the set of live tokens is the set of reachable services.
"""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass

import zenoh

from navi_contracts.topics import ALIVE, alive_key


@dataclass(frozen=True)
class LiveToken:
    """One live service instance."""

    service: str
    instance: str

    @property
    def key(self) -> str:
        return alive_key(self.service, self.instance)


def instance_id() -> str:
    """A per-process id: host name and pid (unique on one host, readable in `navi stack status`)."""
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


def declare_alive(sess: zenoh.Session, service: str, instance: str | None = None) -> zenoh.LivelinessToken:
    """Declare this process's token; keep the returned object alive as long as the service runs."""
    return sess.liveliness().declare_token(alive_key(service, instance or instance_id()))


def parse_token(key: str, prefix: str = ALIVE) -> LiveToken | None:
    """`<prefix>/<service>/<instance>` -> LiveToken, None for anything else."""
    head = prefix.rstrip("/") + "/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) != 2 or not all(parts):
        return None
    return LiveToken(parts[0], parts[1])


def live_tokens(
    sess: zenoh.Session, service: str = "*", timeout_s: float = 1.0, prefix: str = ALIVE
) -> list[LiveToken]:
    """The live tokens under `prefix` (of one service, or all), sorted by service then instance."""
    replies = sess.liveliness().get(f"{prefix}/{service}/*", timeout=timeout_s)
    found = set()
    for reply in replies:
        if reply.ok is not None:
            token = parse_token(str(reply.ok.key_expr), prefix)
            if token is not None:
                found.add(token)
    return sorted(found, key=lambda t: (t.service, t.instance))
