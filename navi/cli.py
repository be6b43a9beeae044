"""The `navi` command: one entry point, one group of sub-commands per service.

Each workspace package contributes its commands through `navi_<package>.cli.register(app, bench)`.
Those modules import only typer and the standard library at import time (heavy imports happen
inside the commands), so `navi --help` stays fast and works on a machine with just torch.
"""

from __future__ import annotations

import importlib
from typing import Annotated

import typer

from navi import __version__, git_commit

COMMAND_MODULES = (
    "navi_compiler.cli",
    "navi_env.cli",
    "navi_learner.cli",
    "navi_auditor.cli",
    "navi_mesh.cli",
)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"navi {__version__} (commit {git_commit()})")
        raise typer.Exit()


def build_app() -> typer.Typer:
    app = typer.Typer(
        name="navi",
        help="Navi: compile 3D scenes into SDF DAGs, trace them on CPU/CUDA, and train drones with PPO.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )
    bench = typer.Typer(
        help="Benchmarks; each prints one JSON object (record results in docs/PERFORMANCE.md).",
        no_args_is_help=True,
    )

    @app.callback()
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

    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        module.register(app, bench)
    app.add_typer(bench, name="bench", rich_help_panel="Benchmarks")
    return app


def main() -> None:
    build_app()()
