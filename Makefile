# Set-up and entry points. Each target creates the virtual environment it needs.
PY      ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: demo test test-all bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

demo: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/pmcal demo

test: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/python -m pytest -n 2 -q

test-all: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/python -m pytest -n 2 -q -m ''

bench: $(STAMP)
	for b in benchmarks/*_bench.py; do MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
