# Navi: one Makefile for the whole workspace.
#   make run    set everything up, then run the main job (procedural corpus -> train -> promote -> evaluate)
#   make test   set everything up, then run the whole test suite
#   make check  lint (ruff), format check, types (mypy), tests
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# Kept as a range so that an installed CPU or CUDA build of torch is reused, never replaced.
TORCH_SPEC ?= torch>=2.5
# The workspace packages and their optional extras are listed in deploy/setup_workspace.py, which does
# the installing: it keeps an installed torch, pins it by its distribution version (the constraint
# every later pip call takes, so nothing can replace it), and skips, with one line, an optional extra
# that cannot resolve against it.
TORCH_PIN := $(VENV)/torch-pin.txt
# Set VENV_FLAGS= to build a venv that does not see the interpreter's site-packages (CI does).
VENV_FLAGS ?= --system-site-packages
PYTEST_ARGS ?=
STAMP := $(VENV)/.navi-setup
SOURCES := $(wildcard pyproject.toml requirements-dev.txt */*/pyproject.toml */*/setup.py */*/*/csrc/* */*/*/*/csrc/*)

.PHONY: help setup run test check lint format typecheck clean

help:
	@echo "make run        set up, then train on the procedural default corpus and evaluate"
	@echo "make test       set up, then run the test suite (gpu tests skip without CUDA)"
	@echo "make check      ruff lint + format check, mypy, pytest"
	@echo "make format     apply ruff format"
	@echo "make clean      remove the virtual environment and build outputs"

setup: $(STAMP)

# By default the venv sees the interpreter's site-packages, so a torch that is already installed is kept.
$(STAMP): $(SOURCES) deploy/setup_workspace.py
	@test -x $(PY) || $(PYTHON) -m venv $(VENV_FLAGS) $(VENV)
	@$(PY) deploy/setup_workspace.py --torch-spec "$(TORCH_SPEC)" --pin $(TORCH_PIN)
	@touch $(STAMP)

run: setup
	$(VENV)/bin/navi run

# The real-map tests need Debian's openarena-081-maps (fetched once into artifacts/data/, no root install);
# where it cannot be had they skip, and pytest's summary names each skipped test and why.
test: setup
	@bash tests/data/fetch_openarena.sh || echo "[navi] the OpenArena maps could not be fetched: the data-marked tests will skip (bash tests/data/fetch_openarena.sh enables them)"
	$(PY) -m pytest $(PYTEST_ARGS)

lint: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

format: setup
	$(PY) -m ruff format .
	$(PY) -m ruff check --fix .

typecheck: setup
	$(PY) -m mypy navi shared/contracts/navi_contracts shared/mesh/navi_mesh services/compiler/navi_compiler \
		services/env/navi_env services/learner/navi_learner services/auditor/navi_auditor benchmarks/navi_bench

check: lint typecheck test

clean:
	rm -rf $(VENV) build */*/build */*/*.egg-info *.egg-info .mypy_cache .ruff_cache .pytest_cache
	find . -name '*.so' -path '*/navi_*' -delete
