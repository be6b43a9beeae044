"""One Zenoh session per process, opened from NaviSettings or a Zenoh JSON5 file.

Clients connect to explicit endpoints with multicast and gossip scouting off. They wait for the
router instead of failing (unless a deadline is given) and reconnect by themselves after a router
restart; Zenoh re-declares their subscribers, queryables and liveliness tokens on the new link.

The session is opened lazily in the process that uses it and reopened after a fork (a Zenoh runtime
does not survive `fork()`), so open it only after any worker processes are started.
"""

from __future__ import annotations

import json
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import zenoh

if TYPE_CHECKING:
    from navi_contracts.settings import NaviSettings

Mode = Literal["client", "router", "peer"]

RETRY_INIT_MS = 200
"""First reconnect delay after the router went away, milliseconds."""
RETRY_MAX_MS = 1000
"""Longest delay between reconnect attempts, milliseconds (a restarted router is found within it)."""


@dataclass(frozen=True)
class SessionConfig:
    """How this process joins the Zenoh network."""

    mode: Mode = "client"
    """client (services), router (`navi serve router`) or peer."""
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    """Endpoints to connect to (a client's router)."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on (the router's)."""
    config_file: Path | None = None
    """A Zenoh JSON5 config file; when set it is used as is and the fields above are ignored."""
    connect_timeout_s: float | None = None
    """None: wait for the router forever; else fail with MeshError after this many seconds."""


class MeshError(RuntimeError):
    """The Zenoh network cannot be joined (bad config, or no router before the deadline)."""


def config_from_settings(
    settings: NaviSettings, mode: Mode = "client", connect_timeout_s: float | None = None
) -> SessionConfig:
    """The session config NAVI_ZENOH_CONNECT / NAVI_ZENOH_LISTEN / NAVI_ZENOH_CONFIG describe."""
    return SessionConfig(
        mode=mode,
        connect=tuple(settings.connect_endpoints) if mode != "router" else (),
        listen=tuple(settings.listen_endpoints) if mode == "router" else (),
        config_file=settings.zenoh_config,
        connect_timeout_s=connect_timeout_s,
    )


def config_json(cfg: SessionConfig) -> dict[str, object]:
    """The Zenoh configuration (as a JSON-able dict) for `cfg` without a config file."""
    timeout_ms = -1 if cfg.connect_timeout_s is None else max(1, round(cfg.connect_timeout_s * 1000))
    admin: dict[str, object] = (
        # read-only, as zenohd's default: a router can read back the port a `:0` endpoint got
        {"adminspace": {"enabled": True, "permissions": {"read": True, "write": False}}}
        if cfg.mode == "router"
        else {}
    )
    return {
        "mode": cfg.mode,
        "connect": {
            "endpoints": list(cfg.connect),
            "timeout_ms": timeout_ms,
            "exit_on_failure": cfg.connect_timeout_s is not None,
            "retry": {
                "period_init_ms": RETRY_INIT_MS,
                "period_max_ms": RETRY_MAX_MS,
                "period_increase_factor": 2.0,
            },
        },
        "listen": {"endpoints": list(cfg.listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        **admin,
    }


def zenoh_config(cfg: SessionConfig) -> zenoh.Config:
    """Build the zenoh.Config for `cfg`."""
    if cfg.config_file is not None:
        if not cfg.config_file.is_file():
            raise MeshError(f"Zenoh config file {cfg.config_file} does not exist")
        try:
            return zenoh.Config.from_file(str(cfg.config_file))
        except zenoh.ZError as err:
            raise MeshError(f"invalid Zenoh config {cfg.config_file}: {err}") from err
    if cfg.mode == "client" and not cfg.connect:
        raise MeshError("a client needs at least one endpoint to connect to (NAVI_ZENOH_CONNECT)")
    try:
        return zenoh.Config.from_json5(json.dumps(config_json(cfg)))
    except zenoh.ZError as err:
        raise MeshError(f"invalid Zenoh endpoints {cfg.connect or cfg.listen}: {err}") from err


def open_new_session(cfg: SessionConfig) -> zenoh.Session:
    """Open a session that this caller owns (the router, tools that need a private one)."""
    try:
        return zenoh.open(zenoh_config(cfg))
    except zenoh.ZError as err:
        where = ", ".join(cfg.connect or cfg.listen) or str(cfg.config_file)
        raise MeshError(f"cannot join the Zenoh network at {where}: {err}") from err


_lock = threading.Lock()
_session: tuple[int, zenoh.Session] | None = None


def _forget_after_fork() -> None:
    global _session
    _session = None


os.register_at_fork(after_in_child=_forget_after_fork)


def session(cfg: SessionConfig) -> zenoh.Session:
    """The process's one session, opened on first use (and again in a forked child)."""
    global _session
    with _lock:
        if _session is not None and _session[0] == os.getpid() and not _session[1].is_closed():
            return _session[1]
        opened = open_new_session(cfg)
        _session = (os.getpid(), opened)
        return opened


def close_session() -> None:
    """Close the process's session (undeclares everything it declared)."""
    global _session
    with _lock:
        if _session is not None and _session[0] == os.getpid():
            _session[1].close()
        _session = None


def router_locators(sess: zenoh.Session, timeout_s: float = 5.0) -> list[str]:
    """The endpoints a router session listens on, as bound (a `tcp/127.0.0.1:0` endpoint shows the port
    the OS picked), read from its own admin space; [] where the admin space is not readable."""
    for reply in sess.get(f"@/{sess.zid()}/router", timeout=timeout_s):
        if reply.ok is not None:
            try:
                locators = json.loads(reply.ok.payload.to_bytes())["locators"]
            except (ValueError, KeyError, TypeError):
                return []
            return [str(x) for x in locators]
    return []
