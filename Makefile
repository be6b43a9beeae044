# Navi: one Makefile for the whole workspace.
#   make run    set everything up, then run the main job (procedural corpus -> train -> promote -> evaluate)
#   make test   set everything up, then run the whole test suite
#   make check  lint (ruff), format check, types (mypy), tests
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip --disable-pip-version-check -q
# Kept as a range so that an installed CPU or CUDA build of torch is reused, never replaced.
TORCH_SPEC ?= torch>=2.5
# navi_env's optional extras (Gymnasium, TorchRL, skrl adapters) are installed too: their tests run in `make test`.
PACKAGES := shared/contracts shared/mesh services/compiler services/env[gym,torchrl,skrl] \
	services/learner[plots,tensorboard] services/auditor
# The torch found (or just installed) is written here and passed to pip as a constraint, so that no
# package of the workspace or its extras can upgrade or replace it: pip fails instead.
TORCH_PIN := $(VENV)/torch-pin.txt
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

# The venv sees the interpreter's site-packages, so a torch that is already installed is kept.
$(STAMP): $(SOURCES)
	@test -x $(PY) || $(PYTHON) -m venv --system-site-packages $(VENV)
	@echo "[navi] installing build tools"
	@$(PIP) install "setuptools>=68" "pybind11>=2.12" wheel
	@$(PY) -c "import torch" 2>/dev/null || { echo "[navi] installing $(TORCH_SPEC)"; $(PIP) install "$(TORCH_SPEC)"; }
	@$(PY) -c "import torch; print('torch==' + torch.__version__)" > $(TORCH_PIN)
	@echo "[navi] installing the workspace packages (builds the C++ extensions), keeping $$(cat $(TORCH_PIN))"
	@$(PIP) install --no-build-isolation -c $(TORCH_PIN) $(foreach p,$(PACKAGES),-e $(p)) -e . -r requirements-dev.txt
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
		services/env/navi_env services/learner/navi_learner services/auditor/navi_auditor

check: lint typecheck test

clean:
	rm -rf $(VENV) build */*/build */*/*.egg-info *.egg-info .mypy_cache .ruff_cache .pytest_cache
	find . -name '*.so' -path '*/navi_*' -delete
