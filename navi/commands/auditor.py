"""Auditor commands: `navi record`, `replay`, `explore` and `bc`.

`navi serve auditor` (the live dashboard) lives in the `serve` group (navi.commands.serve) and calls
`navi_auditor.server.serve(host, port, settings)`. Module-level imports: typer and the standard library.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated

import typer

from navi.commands.common import fail
from navi.commands.options import Settings, config_options
from navi_learner.config import EngineConfig

PANEL = "Auditor"
app = typer.Typer()
"""Merged into the root: `navi record`, `replay`, `explore`, `bc`."""
DEFAULT_TOPICS = ("observations", "actions", "telemetry")


def _stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (so recordings and replays end cleanly)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


@app.command("record", rich_help_panel=PANEL)
def record_command(
    out: Annotated[Path, typer.Option("--out", help="New Zarr v3 session store to create (SESSION.zarr).")],
    topics: Annotated[
        list[str] | None,
        typer.Option(
            "--topics",
            help="Topics to record (repeatable): observations, actions, telemetry, "
            "model_promoted. Default: observations, actions, telemetry.",
        ),
    ] = None,
    duration: Annotated[
        float | None, typer.Option("--duration", help="Stop after this many seconds (default: until Ctrl+C).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON summary object on stdout.")] = False,
) -> None:
    """Record Zenoh streams into a Zarr v3 session store (flushed every second; survives being killed)."""
    from navi_auditor.feed import open_until
    from navi_auditor.recorder import record, topic_names
    from navi_contracts.settings import NaviSettings

    try:
        chosen = topic_names(topics or list(DEFAULT_TOPICS))
    except ValueError as exc:
        raise fail(str(exc)) from exc
    if out.exists():
        raise fail(f"{out} already exists; recordings never overwrite")
    if duration is not None and duration <= 0:
        raise fail("--duration must be positive")
    stop = _stop_on_signals()
    typer.echo("waiting for the Zenoh router (Ctrl+C to give up)", err=True)
    session = open_until(NaviSettings(), stop)
    if session is None:
        raise typer.Exit(1)

    def ready() -> None:
        typer.echo(f"recording {', '.join(chosen)} into {out} (Ctrl+C to stop)", err=True)

    try:
        writer = record(out, chosen, duration, session, stop=stop, on_ready=ready)
    finally:
        session.close()
    summary = {
        "out": str(out),
        "messages": writer.written,
        "rejected": writer.rejected,
        "duration_s": round(writer.now(), 3),
        "topics": chosen,
    }
    typer.echo(json.dumps(summary) if as_json else f"recorded {writer.written} messages to {out}")


@app.command("replay", rich_help_panel=PANEL)
def replay_command(
    session_path: Annotated[Path, typer.Argument(help="A session store written by `navi record`.")],
    rate: Annotated[float, typer.Option("--rate", help="Playback speed: 2.0 plays twice as fast.")] = 1.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON summary object on stdout.")] = False,
) -> None:
    """Republish a recorded session on Zenoh with its original timing (the dashboard shows it as live)."""
    from navi_auditor.feed import open_until
    from navi_auditor.replay import SessionFormatError, SessionReader, replay, schedule, zenoh_publisher
    from navi_contracts.settings import NaviSettings

    if rate <= 0:
        raise fail("--rate must be positive")
    try:
        entries = schedule(SessionReader(session_path))
    except SessionFormatError as exc:
        raise fail(str(exc)) from exc
    stop = _stop_on_signals()
    session = open_until(NaviSettings(), stop)
    if session is None:
        raise typer.Exit(1)
    span = entries[-1][0] - entries[0][0] if entries else 0.0
    typer.echo(f"replaying {len(entries)} messages over {span / rate:.1f} s", err=True)
    try:
        stats = replay(entries, zenoh_publisher(session), rate, stop)
    finally:
        session.close()
    summary = {
        "session": str(session_path),
        "messages": stats.messages,
        "wall_s": round(stats.wall_s, 3),
        "max_lag_s": round(stats.max_lag_s, 4),
        "rate": rate,
    }
    typer.echo(
        json.dumps(summary) if as_json else f"replayed {stats.messages} messages in {stats.wall_s:.1f} s"
    )


@app.command("explore", rich_help_panel=PANEL)
def explore_command(
    gmdag: Annotated[Path | None, typer.Option("--gmdag", help="Fly this one .gmdag scene.")] = None,
    corpus: Annotated[
        Path | None, typer.Option("--corpus", help="Fly every .gmdag in this folder, by name.")
    ] = None,
    max_steps: Annotated[
        int, typer.Option("--max-steps", help="Steps per scene before the next opens.")
    ] = 600,
    out_dir: Annotated[
        Path, typer.Option("--out", help="Folder for the recorded demonstrations (.npz).")
    ] = Path("artifacts/demonstrations"),
    host: Annotated[str, typer.Option("--host", help="Address the explorer page listens on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", help="Port of the explorer page.")] = 8080,
    device: Annotated[str, typer.Option("--device", help="Torch device of the environment.")] = "cpu",
    obstacles: Annotated[
        int,
        typer.Option(
            "--obstacles", min=0, max=64, help="Scripted moving obstacles around the drone (tinted)."
        ),
    ] = 0,
) -> None:
    """Fly a drone through scenes with the keyboard in the browser; every flight is saved as a demonstration."""
    if (gmdag is None) == (corpus is None):
        raise fail("give exactly one of --gmdag FILE or --corpus DIR")
    if max_steps < 1:
        raise fail("--max-steps must be at least 1")
    if gmdag is not None and not gmdag.is_file():
        raise fail(f"{gmdag} is not a file")
    if corpus is not None and not corpus.is_dir():
        raise fail(f"{corpus} is not a folder")
    paths = [gmdag] if gmdag is not None else sorted(corpus.glob("*.gmdag")) if corpus is not None else []
    if not paths:
        raise fail(f"no .gmdag scenes in {corpus}")

    from navi_auditor.explorer import run_explorer

    saved = run_explorer(paths, max_steps, out_dir, host, port, device, obstacles)
    typer.echo(f"saved {len(saved)} demonstration(s) under {out_dir}")


@app.command("bc", rich_help_panel=PANEL)
@config_options(EngineConfig(), ("temporal_core",))
def bc_command(
    *,
    demos: Annotated[Path, typer.Option("--demos", help="Folder of demonstration .npz files.")],
    out: Annotated[Path, typer.Option("--out", help="Checkpoint to write (v3, training_source=bc).")],
    epochs: Annotated[int, typer.Option("--epochs", help="Passes over the demonstrations.")] = 20,
    bptt: Annotated[int, typer.Option("--bptt", help="Truncated-BPTT chunk length (steps).")] = 32,
    streams: Annotated[int, typer.Option("--streams", help="Parallel sequences per batch.")] = 8,
    lr: Annotated[float, typer.Option("--lr", help="Adam learning rate.")] = 5e-4,
    settings: Settings,
    device: Annotated[str, typer.Option("--device", help="Torch device: cpu, cuda, cuda:N.")] = "cpu",
    seed: Annotated[int, typer.Option("--seed", help="Seed for the weights.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON summary object on stdout.")] = False,
) -> None:
    """Behavioural cloning: train CognitiveMambaPolicy on demonstrations; `navi train --checkpoint OUT` fine-tunes it."""
    temporal_core = settings["temporal_core"]
    if temporal_core not in ("mamba2", "gru", "mambapy"):
        raise fail(f"unknown temporal core {temporal_core!r}; choose mamba2, gru or mambapy")
    if min(epochs, bptt, streams) < 1 or lr <= 0:
        raise fail("--epochs, --bptt and --streams must be at least 1 and --lr positive")
    if not demos.is_dir():
        raise fail(f"{demos} is not a folder")

    import torch

    from navi_auditor.bc import BCConfig, run_bc
    from navi_auditor.demos import DemoFormatError, load_demos

    if device.startswith("cuda") and not torch.cuda.is_available():
        raise fail(f"device {device} requested but CUDA is not available")
    try:
        loaded = load_demos(demos)
    except DemoFormatError as exc:
        raise fail(str(exc)) from exc
    engine: EngineConfig = settings.config()
    _, az, el = loaded[0].obs_shape
    try:
        engine.patch_for(az, el)
    except ValueError as err:
        raise fail(str(err)) from err
    config = BCConfig(epochs=epochs, bptt=bptt, streams=streams, lr=lr, seed=seed, device=device)

    def progress(epoch: int, loss: float) -> None:
        if sys.stderr.isatty() or not as_json:
            typer.echo(f"epoch {epoch + 1}/{epochs}  bc loss {loss:.5f}", err=True)

    summary = run_bc(loaded, out, engine, config, progress)
    typer.echo(json.dumps(summary) if as_json else f"wrote {out} (bc loss {summary['final_loss']:.5f})")
