"""`navi stack up|down|status`: the whole stack (router, compiler, env, learner, auditor) as local
processes with the same commands and config as the compose stack (navi.stack runs them)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

from navi.commands.common import fail
from navi.commands.serve import CorpusOpt, load_settings

app = typer.Typer(
    help="The whole stack as local processes: router, compiler, env, learner, auditor.", no_args_is_help=True
)


def _print_status(cfg_root: Path, connect: tuple[str, ...], as_json: bool, timeout_s: float) -> None:
    from navi.stack import learner_health, read_states
    from navi_mesh.liveliness import live_tokens
    from navi_mesh.session import MeshError, SessionConfig, open_new_session

    states = read_states(cfg_root)
    health = learner_health(cfg_root) if any(s.name == "learner" and s.running for s in states) else None
    tokens: list[str] = []
    error = ""
    try:
        sess = open_new_session(SessionConfig(connect=connect, connect_timeout_s=timeout_s))
    except MeshError as err:
        error = str(err)
    else:
        try:
            tokens = [t.key for t in live_tokens(sess, timeout_s=timeout_s)]
        finally:
            sess.close()
    if as_json:
        typer.echo(
            json.dumps(
                {
                    "processes": [
                        {"name": s.name, "pid": s.pid, "running": s.running, "log": s.log} for s in states
                    ],
                    "alive": tokens,
                    "router_error": error,
                    "learner": health,
                }
            )
        )
        return
    if not states:
        typer.echo(f"no stack processes under {cfg_root}")
    for s in states:
        since = time.strftime("%H:%M:%S", time.localtime(s.started_at))
        typer.echo(
            f"{s.name:<9} pid {s.pid:<8} {'running' if s.running else 'stopped':<8} since {since}  {s.log}"
        )
    if health is not None:
        corpus = health.get("corpus")
        line = f"learner: {health.get('phase') or '?'}"
        if isinstance(corpus, dict):
            line += (
                f"; corpus {corpus.get('state')}: {corpus.get('scenes_ready')}/{corpus.get('scenes_total')} "
                f"scenes ready, {corpus.get('rejected')} rejected"
            )
            if corpus.get("error"):
                line += f" ({corpus['error']})"
        typer.echo(line)
    typer.echo(f"live tokens ({len(tokens)}):" if not error else f"router unreachable: {error}")
    for key in tokens:
        typer.echo(f"  {key}")


@app.command("up")
def stack_up(
    corpus: CorpusOpt = Path("artifacts/corpus/default"),
    actors: Annotated[int, typer.Option("--actors", min=1, help="Learner actors (per rank).")] = 4,
    nproc: Annotated[
        int, typer.Option("--nproc", min=1, help="Learner data-parallel ranks, one per GPU (DD-PPO).")
    ] = 1,
    env_actors: Annotated[int, typer.Option("--env-actors", min=1, help="Env-service actors.")] = 2,
    device: Annotated[
        str,
        typer.Option(
            "--device",
            help="Torch device of learner, env and compiler (auto: CUDA and the GPU compile engine when present).",
        ),
    ] = "auto",
    host: Annotated[
        str,
        typer.Option(
            "--host",
            help="Interface every service binds: 127.0.0.1 (this machine only) or 0.0.0.0 (all; then set "
            "NAVI_API_TOKEN yourself and mind your firewall).",
        ),
    ] = "127.0.0.1",
    router_port: Annotated[int, typer.Option("--router-port", help="Zenoh router port.")] = 7447,
    api_port: Annotated[
        int | None, typer.Option("--api-port", help="Control plane port (NAVI_API_PORT).")
    ] = None,
    auditor_port: Annotated[
        int | None, typer.Option("--auditor-port", help="Auditor dashboard port (NAVI_AUDITOR_PORT).")
    ] = None,
    compiler_metrics_port: Annotated[
        int, typer.Option("--compiler-metrics-port", help="Compiler GET /metrics port.")
    ] = 9101,
    env_metrics_port: Annotated[
        int, typer.Option("--env-metrics-port", help="Env GET /metrics port.")
    ] = 9102,
    auditor: Annotated[
        bool, typer.Option("--auditor/--no-auditor", help="Start the auditor dashboard.")
    ] = True,
    corpus_scenes: Annotated[
        int, typer.Option("--corpus-scenes", min=1, help="Scenes of the default corpus when it is built.")
    ] = 16,
    corpus_resolution: Annotated[
        int | None,
        typer.Option("--corpus-resolution", min=8, help="Its resolution (default NAVI_GMDAG_RESOLUTION)."),
    ] = None,
    compiler_workers: Annotated[
        int, typer.Option("--compiler-workers", min=1, help="Compile worker threads.")
    ] = 1,
    wait_s: Annotated[
        float, typer.Option("--wait", min=0.0, help="Seconds to wait for every service's health check.")
    ] = 60.0,
) -> None:
    """Start router, compiler, env, learner (and auditor) at once as local processes (pid files in
    artifacts/stack); returns when each answers its health check. A missing corpus is built in the
    background over compile jobs; training starts when it is ready (`navi stack status` shows progress)."""
    from navi.stack import STACK_DIR, StackConfig, StackError, probe_host, up

    settings = load_settings()
    cfg = StackConfig(
        root=STACK_DIR,
        host=host,
        router_port=router_port,
        api_port=api_port or settings.api_port,
        auditor_port=auditor_port or settings.auditor_port,
        compiler_metrics_port=compiler_metrics_port,
        env_metrics_port=env_metrics_port,
        corpus=corpus,
        corpus_scenes=corpus_scenes,
        corpus_resolution=corpus_resolution or settings.gmdag_resolution,
        compiler_workers=compiler_workers,
        actors=actors,
        nproc=nproc,
        env_actors=env_actors,
        device=device,
        auditor=auditor,
    )
    try:
        up(cfg, wait_s, lambda line: typer.echo(line, err=True), typer.echo)
    except StackError as err:
        raise fail(str(err)) from err
    _print_status(cfg.root, (f"tcp/{probe_host(host)}:{router_port}",), False, 2.0)


@app.command("down")
def stack_down(
    grace_s: Annotated[
        float, typer.Option("--grace", min=0.0, help="Seconds between SIGTERM and SIGKILL.")
    ] = 30.0,
) -> None:
    """Stop every stack process (SIGTERM, then SIGKILL after the grace period)."""
    from navi.stack import STACK_DIR, stop_all

    states = stop_all(STACK_DIR, grace_s)
    if not states:
        typer.echo("no stack processes")
    for s in states:
        typer.echo(f"{s.name:<9} pid {s.pid:<8} {'STILL RUNNING' if s.running else 'stopped'}")


@app.command("status")
def stack_status(
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    timeout_s: Annotated[
        float, typer.Option("--timeout", min=0.1, help="Seconds to wait for the router.")
    ] = 2.0,
) -> None:
    """Process states (pid files) and the live liveliness tokens (navi/alive/<service>/<id>)."""
    from navi.stack import STACK_DIR

    _print_status(STACK_DIR, tuple(load_settings().connect_endpoints), as_json, timeout_s)
