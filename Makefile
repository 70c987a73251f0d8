# Two entry points: `make demo` (the main job) and `make test` (ruff, mypy, pytest).
# Each creates .venv with Python 3.11 and installs what it needs.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test install clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(BIN)/python -m normpos_grasp.templates.warmup  # compile the fit kernels once (numba cache)
	touch $@

install: $(BIN)/.installed

demo: install
	$(BIN)/normpos-grasp demo --out demo_out

test: install
	$(BIN)/ruff check normpos_grasp tests benchmarks examples robots
	$(BIN)/mypy
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) build *.egg-info demo_out
