"""Environment commands: `navi qualify` (judge one scene's spawns) and the `navi corpus build|list` group."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from navi.commands.common import fail

PANEL = "Environment"
app = typer.Typer()
"""Merged into the root: `navi qualify`, and `navi corpus` as a group."""


def _say(line: str) -> None:
    if sys.stderr.isatty():
        typer.echo(line, err=True)


corpus = typer.Typer(help="Training corpora: folders of qualified .gmdag scenes.", no_args_is_help=True)


@app.command("qualify", rich_help_panel=PANEL)
def qualify(
    file: Annotated[Path, typer.Argument(help="The .gmdag scene to judge.")],
    json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")] = False,
    device: Annotated[str, typer.Option(help="Device that traces the probe rays (cpu, cuda).")] = "cpu",
) -> None:
    """Probe a 5x7x5 grid of spawn candidates with 48x12 rays; exit 1 when the scene fails."""
    from navi_compiler.gmdag import GmdagError
    from navi_env.space.qualify import qualify_scene
    from navi_env.tracer.scene import load_scene

    if not file.is_file():
        raise fail(f"file not found: {file}")
    try:
        corpus = load_scene(file, device)
    except (GmdagError, OSError, RuntimeError, ValueError) as exc:
        raise fail(f"{file}: {exc}") from exc
    result = qualify_scene(corpus, 0)
    if json_out:
        typer.echo(json.dumps({"file": str(file), **result.to_json()}))
    else:
        typer.echo(f"{file}: {result.verdict.upper()} - {result.reason}")
        typer.echo(
            f"  viable spawns {result.viable_spawns} / {result.candidates} candidates "
            f"({result.free_candidates} free), best starvation {result.best_starvation:.3f}, "
            f"trace cost {result.trace_cost:.2f} steps per ray"
        )
    if not result.passed:
        raise typer.Exit(1)


@corpus.command("build")
def corpus_build(
    out: Annotated[Path, typer.Option("--out", "-o", help="Corpus folder to create or replace.")],
    src_dir: Annotated[
        Path | None, typer.Argument(help="Folder of scene sources (meshes, .bsp, .pk3, .gmdag).")
    ] = None,
    default: Annotated[bool, typer.Option("--default", help="Build the procedural default corpus.")] = False,
    resolution: Annotated[
        int, typer.Option(help="Cells per cube edge of every compiled scene.", min=8)
    ] = 512,
    count: Annotated[int, typer.Option(help="Procedural scenes to generate with --default.", min=1)] = 16,
    seed: Annotated[int, typer.Option(help="Seed of the procedural scenes with --default.")] = 0,
    device: Annotated[str, typer.Option(help="Device that traces the qualification rays.")] = "cpu",
    workers: Annotated[
        int,
        typer.Option(
            help="Sources compiled at once, each in a process of its own (0: one per CPU core, as many as"
            " memory holds; 1 below 256 cells, where a process costs more than it saves).",
            min=0,
        ),
    ] = 0,
    json_out: Annotated[bool, typer.Option("--json", help="Print the manifest summary as JSON.")] = False,
) -> None:
    """Compile, check and qualify every source into OUT; the old corpus is replaced only on success."""
    from navi_env.corpus.folder import CorpusError, build_corpus, build_default_corpus, find_sources

    if default == (src_dir is not None):
        raise fail("give either SRC_DIR or --default")
    try:
        if src_dir is None:
            manifest = build_default_corpus(
                out, resolution, count, seed, device, progress=_say, workers=workers
            )
        else:
            sources = find_sources(src_dir)
            if not sources:
                raise fail(f"no scene sources found in {src_dir}")
            manifest = build_corpus(sources, out, resolution, device, progress=_say, workers=workers)
    except CorpusError as exc:
        raise fail(f"{exc} (the previous corpus at {out} is unchanged)") from exc
    summary = {"corpus": str(out), **manifest.summary()}
    if json_out:
        typer.echo(json.dumps(summary))
    else:
        typer.echo(f"{out}: {len(manifest.scenes)} scenes, {len(manifest.rejected)} rejected")


@corpus.command("list")
def corpus_list(
    corpus: Annotated[Path, typer.Argument(help="Corpus folder.")],
    json_out: Annotated[bool, typer.Option("--json", help="Print the manifest as JSON.")] = False,
) -> None:
    """List a corpus's scenes with their size and qualification."""
    from navi_env.corpus.folder import CorpusError, read_manifest

    try:
        manifest = read_manifest(corpus)
    except CorpusError as exc:
        raise fail(str(exc)) from exc
    if json_out:
        typer.echo(json.dumps(manifest.to_json()))
        return
    typer.echo(f"{corpus}: {len(manifest.scenes)} scenes (built {manifest.created_at})")
    for s in manifest.scenes:
        q = s.qualification
        typer.echo(
            f"  {s.name:<28} {s.resolution:>5}^3  {s.voxel_size:8.4f} m  {s.bytes / 1e6:8.2f} MB  "
            f"spawns {q.get('viable_spawns')}  best starvation {q.get('best_starvation')}"
            + (f"  trace cost {s.trace_cost():.2f}" if s.trace_cost() > 0.0 else "")
            + (f"  obstacles {s.obstacles}" if s.obstacles else "")
        )
    for r in manifest.rejected:
        typer.echo(f"  rejected {r['source']}: {r['reason']}")


app.add_typer(corpus, name="corpus", rich_help_panel=PANEL)
