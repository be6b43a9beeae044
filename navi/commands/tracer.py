"""Tracer commands: `navi raycast` (depths of given rays through one .gmdag scene, to .npy)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from navi.commands.common import fail

app = typer.Typer()
"""Merged into the root: `navi raycast`."""


@app.command("raycast", rich_help_panel="Tracer")
def raycast(
    gmdag: Annotated[Path, typer.Argument(help="Scene file (.gmdag).")],
    origins: Annotated[
        Path, typer.Option("--origins", help="(N, 3) float32 .npy of ray origins, world meters.")
    ],
    dirs: Annotated[
        Path, typer.Option("--dirs", help="(N, R, 3) or (R, 3) float32 .npy of unit directions.")
    ],
    out: Annotated[Path, typer.Option("-o", "--out", help="Where to write the (N, R) float32 depth .npy.")],
    device: Annotated[str, typer.Option(help="cpu, cuda or cuda:N.")] = "cpu",
    max_steps: Annotated[int, typer.Option(help="Sphere-tracing steps per ray.")] = 256,
    horizon: Annotated[float, typer.Option(help="Meters; a miss reports this depth.")] = 100.0,
    semantic_out: Annotated[
        Path | None,
        typer.Option("--semantic-out", help="Also write (N, R) int32 semantic (0 miss, 1+class)."),
    ] = None,
) -> None:
    """Depth along your own rays through a .gmdag scene (horizon on a miss)."""
    import numpy as np
    import torch

    from navi_compiler.gmdag import GmdagError
    from navi_env.tracer.scene import load_scene
    from navi_env.tracer.trace import trace

    try:
        o = np.load(origins)  # (N, 3)
        d = np.load(dirs)  # (N, R, 3) or (R, 3)
    except (OSError, ValueError) as exc:
        raise fail(f"cannot read the .npy inputs: {exc}") from None
    if o.ndim != 2 or o.shape[1] != 3:
        raise fail(f"--origins must be (N, 3), got {o.shape}")
    if not (d.ndim == 2 and d.shape[1] == 3) and not (
        d.ndim == 3 and d.shape[0] == o.shape[0] and d.shape[2] == 3
    ):
        raise fail(f"--dirs must be (R, 3) or ({o.shape[0]}, R, 3), got {d.shape}")
    try:
        dev = torch.device(device)
        corpus = load_scene(gmdag, dev)
    except (OSError, GmdagError, RuntimeError) as exc:
        raise fail(str(exc)) from None
    n, r = o.shape[0], d.shape[-2]
    depth = torch.empty(n, r, device=dev)  # (N, R) float32
    sem = torch.empty(n, r, dtype=torch.int32, device=dev)  # (N, R) int32
    try:
        trace(
            corpus,
            torch.zeros(n, dtype=torch.int64, device=dev),
            torch.from_numpy(np.ascontiguousarray(o, np.float32)).to(dev),
            torch.from_numpy(np.ascontiguousarray(d, np.float32)).to(dev),
            out_depth=depth,
            out_semantic=sem,
            max_steps=max_steps,
            horizon=horizon,
        )
    except (ValueError, TypeError, RuntimeError) as exc:
        raise fail(str(exc)) from None
    np.save(out, depth.cpu().numpy())
    if semantic_out is not None:
        np.save(semantic_out, sem.cpu().numpy())
    hits = float((sem > 0).float().mean())
    typer.echo(f"wrote {out} ({n} x {r} depths, {hits:.1%} hits)", err=True)
