"""`navi` with the hot-path packages only (compiler, env, learner), for CUDA hosts without the service
packages (our lent GPU machines): `python tests/navi_device.py bench learn ...`. tests/gpu_env.sh puts
the packages on PYTHONPATH and defines `navi` as this script."""

from __future__ import annotations

import typer

from navi_compiler.cli import register as register_compiler
from navi_env.cli import register as register_env
from navi_learner.cli import register as register_learner

app = typer.Typer(no_args_is_help=True)
bench = typer.Typer(no_args_is_help=True)
for register in (register_compiler, register_env, register_learner):
    register(app, bench)
app.add_typer(bench, name="bench")

if __name__ == "__main__":
    app()
