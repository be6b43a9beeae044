"""`navi soak`: the local stack under overlapping faults for N minutes, then a table of what held."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from navi.commands.common import fail

app = typer.Typer()
PANEL = "Services"


@app.command("soak", rich_help_panel=PANEL)
def soak_cmd(
    minutes: Annotated[
        float,
        typer.Option(
            "--minutes", min=0.5, help="How long faults are injected (start-up and checks come on top)."
        ),
    ] = 5.0,
    seed: Annotated[
        int, typer.Option("--seed", help="Seed of the fault schedule and the garbage payloads.")
    ] = 0,
    out: Annotated[
        Path, typer.Option("--out", help="The soak's folder: stack logs, runs, models, corpus and soak.json.")
    ] = Path("artifacts/soak"),
    base_port: Annotated[
        int,
        typer.Option(
            "--base-port", min=1024, max=65530, help="Router port; the next four serve the HTTP ends."
        ),
    ] = 17447,
    fault_gap_s: Annotated[
        float, typer.Option("--fault-gap-s", min=1.0, help="Mean seconds between two faults' starts.")
    ] = 8.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as one JSON object.")] = False,
) -> None:
    """Bring up the local stack on loopback (CPU, a small procedural corpus), train, and inject seeded,
    overlapping faults: SIGKILL and restart of each service in turn (the learner resumes from its newest
    checkpoint), SIGSTOP/SIGCONT of the env, garbage on every subscribed topic, bad REST requests,
    promotions and rollbacks while checkpoints are written, and an archive-bomb compile job. Then check
    that no env step was lost beyond the newest checkpoint, every checkpoint and registry file loads, the
    registry matches its files, memory and file descriptors stay flat across restarts, tokens come back,
    every bad input was counted or refused, and the dashboard and every /metrics answer. Exits 1 when a
    check fails; the report is also written to OUT/soak.json."""
    from navi.soak import SoakConfig, SoakError, soak, table

    cfg = SoakConfig(minutes=minutes, seed=seed, root=out, base_port=base_port, fault_gap_s=fault_gap_s)
    say = (lambda _: None) if as_json else (lambda line: typer.echo(f"[soak] {line}"))
    try:
        report = soak(cfg, say)
    except SoakError as err:
        raise fail(str(err)) from None
    if as_json:
        typer.echo(json.dumps(report, default=str))
    else:
        typer.echo(table(report))
        typer.echo(f"[soak] {'passed' if report['passed'] else 'FAILED'}; report in {out / 'soak.json'}")
    if not report["passed"]:
        raise typer.Exit(1)
