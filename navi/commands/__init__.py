"""The command groups of `navi`, one module each, each a module-level typer app of top-level command
functions: compiler, scenes, tracer, env (with the corpus group), learner, models, auditor, serve,
stack, bench. common.py holds the options and checks they share. Modules import typer and the standard
library only at import time; each command imports what it needs when it runs.
"""
