"""`navi models list|promote|rollback`: the model registry (artifacts/models) from the command line."""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import Annotated

import typer

from navi.commands.common import MODELS_DIR, JsonOpt, fail

app = typer.Typer(help="The model registry (artifacts/models).", no_args_is_help=True)


@app.command(name="list")
def models_list(
    as_json: JsonOpt = False,
) -> None:
    """List registered versions and aliases."""
    from navi_learner.serving.registry import ModelRegistry

    reg = ModelRegistry(MODELS_DIR)
    entries, aliases = reg.list(), reg.aliases()
    if as_json:
        typer.echo(json.dumps({"versions": [asdict(e) for e in entries], "aliases": aliases}))
        return
    by_version: dict[str, list[str]] = {}
    for alias, version in aliases.items():
        by_version.setdefault(version, []).append(alias)
    for e in entries:
        tags = ",".join(e.tags)
        typer.echo(
            f"{e.version}  step {e.step_id:>12,}  reward_ema {e.reward_ema:+.4f}  {e.temporal_core:8} "
            f"{e.training_source:3} [{tags}] {' '.join(by_version.get(e.version, []))}  {e.notes}"
        )


@app.command(name="promote")
def models_promote(
    checkpoint: Annotated[str, typer.Argument(help="Checkpoint file or an existing version.")],
    alias: Annotated[
        str, typer.Option("--alias", help="Alias to move (latest follows the best).")
    ] = "latest",
    notes: Annotated[str, typer.Option("--notes", help="Free text stored with the version.")] = "",
    tags: Annotated[str, typer.Option("--tags", help="Comma-separated tags.")] = "",
) -> None:
    """Copy a checkpoint into the registry as a new immutable version and move an alias."""
    from navi_learner.serving.registry import ModelRegistry, RegistryError

    try:
        entry = ModelRegistry(MODELS_DIR).promote(checkpoint, alias, notes, [t for t in tags.split(",") if t])
    except RegistryError as err:
        raise fail(str(err)) from err
    typer.echo(json.dumps(asdict(entry)))


@app.command(name="rollback")
def models_rollback(alias: Annotated[str, typer.Argument(help="Alias to move back.")] = "latest") -> None:
    """Point an alias back at its previous version."""
    from navi_learner.serving.registry import ModelRegistry, RegistryError

    try:
        entry = ModelRegistry(MODELS_DIR).rollback(alias)
    except RegistryError as err:
        raise fail(str(err)) from err
    typer.echo(json.dumps(asdict(entry)))
