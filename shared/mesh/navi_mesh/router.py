"""`navi serve router`: a Zenoh router inside this Python process (for machines without zenohd).

The compose stack runs the `eclipse/zenoh` image with deploy/zenoh/router.json5 instead; both listen
on the same endpoint, so services cannot tell them apart.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from pathlib import Path

from navi_mesh.liveliness import declare_alive
from navi_mesh.session import SessionConfig, open_new_session, router_locators

log = logging.getLogger("navi_mesh.router")


@dataclass(frozen=True)
class RouterConfig:
    """Where the router listens."""

    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    """Endpoints to listen on (NAVI_ZENOH_LISTEN)."""
    config_file: Path | None = None
    """A Zenoh JSON5 router config (e.g. deploy/zenoh/router.json5); overrides `listen`."""


def run_router(cfg: RouterConfig, stop: threading.Event) -> None:
    """Run the router until `stop` is set; it holds the token navi/alive/router/<id>."""
    session_cfg = SessionConfig(mode="router", connect=(), listen=cfg.listen, config_file=cfg.config_file)
    sess = open_new_session(session_cfg)
    token = declare_alive(sess, "router")
    bound = router_locators(sess) or list(cfg.listen)  # as bound: a `:0` endpoint shows its port
    log.info("zenoh router %s listening on %s", sess.zid(), ", ".join(bound))
    try:
        stop.wait()
    finally:
        token.undeclare()
        sess.close()
