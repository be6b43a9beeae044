"""The `navi` command: one entry point over the command groups in navi.commands.

Each group is a module with a module-level typer app of top-level command functions. Groups whose
commands sit at the root (`navi compile`, `navi train`, ...) are merged; the others are named
sub-commands (`navi corpus build`, `navi bench trace`, ...). Command modules import only typer and the
standard library at import time (heavy imports happen inside the commands), so `navi --help` stays fast
and works on a machine with just torch.
"""

from __future__ import annotations

from typing import Annotated

import typer

from navi import __version__, git_commit
from navi.commands import auditor, bench, compiler, env, learner, models, scenes, serve, soak, stack, tracer

MERGED = (compiler.app, tracer.app, env.app, learner.app, auditor.app, soak.app)
"""Groups whose commands are added at the root, each under its own help panel."""
NAMED = (
    ("scenes", scenes.app, "Compiler"),
    ("models", models.app, "Learner"),
    ("serve", serve.app, "Services"),
    ("stack", stack.app, "Services"),
    ("bench", bench.app, "Benchmarks"),
)
"""Sub-command groups: (name, app, help panel)."""


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"navi {__version__} (commit {git_commit()})")
        raise typer.Exit()


def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            help="Print the version and git commit, then exit.",
            callback=_version_callback,
            is_eager=True,
        ),
    ] = False,
) -> None:
    """Navi command line."""


def build_app() -> typer.Typer:
    """The root app: every command group attached once."""
    app = typer.Typer(
        name="navi",
        help="Navi: compile 3D scenes into SDF DAGs, trace them on CPU/CUDA, and train drones with PPO.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )
    app.callback()(_root)
    for group in MERGED:
        app.add_typer(group)
    for name, group, panel in NAMED:
        app.add_typer(group, name=name, rich_help_panel=panel)
    return app


def main() -> None:
    build_app()()
