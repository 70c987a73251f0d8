# Two entry points: `make demo` (the main job) and `make test` (ruff, mypy, pytest).
# Each creates .venv with Python 3.11 and installs exactly the versions pinned (with hashes) in requirements.lock.
# `make lock` refreshes requirements.lock from pyproject.toml's ranges (see docs/install.md).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
PIP_VERSION := 26.3
PIP_TOOLS_VERSION := 7.6.2

.PHONY: demo test install lock clean

$(BIN)/.installed: pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet pip==$(PIP_VERSION)
	$(BIN)/python -m pip install --quiet --require-hashes --no-deps -r requirements.lock
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	$(BIN)/python -m pip check
	$(BIN)/python -m normpos_grasp.warmup  # compile the fit kernels and the IK once, store template preparations
	touch $@

install: $(BIN)/.installed

demo: install
	$(BIN)/normpos-grasp demo --out demo_out

test: install
	$(BIN)/ruff check normpos_grasp tests benchmarks examples robots
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 --dist loadfile  # two workers; a test file stays in one (its fixtures too)

lock:
	$(PYTHON) -m venv .lockenv
	.lockenv/bin/python -m pip install --quiet pip==$(PIP_VERSION) pip-tools==$(PIP_TOOLS_VERSION)
	.lockenv/bin/pip-compile pyproject.toml --extra test --generate-hashes --allow-unsafe --all-build-deps \
		--strip-extras --no-emit-index-url --no-emit-find-links --quiet --output-file requirements.lock
	rm -rf .lockenv

clean:
	rm -rf $(VENV) build *.egg-info demo_out
