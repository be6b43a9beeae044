"""`navi scenes generate`: the procedural default corpus written as meshes."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Annotated

import typer


def _parse_families(raw: list[str] | None) -> list[str] | None:
    """Split repeated and comma-separated `--families` values; None keeps the default corpus's families."""
    if not raw:
        return None
    names = [name.strip() for item in raw for name in item.split(",") if name.strip()]
    return names or None


app = typer.Typer(help="Procedural scenes: the embedded default corpus (no download).", no_args_is_help=True)


@app.command("generate")
def generate(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder the scenes are written to.")],
    count: Annotated[int, typer.Option(help="Number of scenes; the families are cycled.", min=1)] = 16,
    seed: Annotated[int, typer.Option(help="Corpus seed; the same seed writes the same files.")] = 0,
    families: Annotated[
        list[str] | None,
        typer.Option(
            help="Families to cycle (repeat or comma-separate); FAMILY@S scales that entry's scenes by up "
            "to S (a factor drawn per scene from the seed). Default: the main job's corpus, every family but "
            "floating and field, then arena@4, platforms@4 and floating@4. See `docs/SCENES.md` for the list.",
        ),
    ] = None,
    semantics: Annotated[
        str,
        typer.Option(
            help="What the face classes name: object (floor, wall, ceiling and each solid's kind) or "
            "surface (floor, wall, ceiling by the face's normal and patch, as Quake 3 maps are classed)."
        ),
    ] = "object",
    json_out: Annotated[
        bool, typer.Option("--json", help="Print one JSON summary object on stdout.")
    ] = False,
) -> None:
    """Write COUNT varied procedural scenes (.obj + .scene.json sidecar) into OUT."""
    from navi_compiler.ingest.procedural import SEMANTICS, generate_corpus, parse_entry

    if semantics not in {s.value for s in SEMANTICS}:
        known = ", ".join(s.value for s in SEMANTICS)
        raise typer.BadParameter(f"unknown semantics {semantics!r}; known: {known}", param_hint="--semantics")

    chosen = _parse_families(families)
    for entry in chosen or []:
        try:
            parse_entry(entry)
        except ValueError as err:
            raise typer.BadParameter(str(err), param_hint="--families") from err
    show = sys.stderr.isatty() and not json_out
    started = time.perf_counter()

    def progress(done: int, total: int, path: Path) -> None:
        if show:
            typer.echo(f"\r[{done}/{total}] {path.name:<40}", err=True, nl=done == total)

    paths = generate_corpus(out, count, seed, families=chosen, progress=progress, semantics=semantics)
    elapsed = time.perf_counter() - started
    family_names = sorted({p.stem.split("_")[0] for p in paths})
    summary = {
        "out": str(out),
        "count": len(paths),
        "seed": seed,
        "families": family_names,
        "semantics": semantics,
        "files": [str(p) for p in paths],
        "seconds": round(elapsed, 3),
    }
    if json_out:
        typer.echo(json.dumps(summary))
    else:
        typer.echo(f"wrote {len(paths)} scenes ({', '.join(family_names)}) to {out} in {elapsed:.1f} s")
