# Set-up commands of the README: `make demo` and `make test` (each installs what it needs first).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# the CPU build of torch on these machines; on a GPU machine use e.g. TORCH=torch
TORCH ?= torch==2.13.0

.PHONY: install demo test benchmark clean

$(VENV)/.installed: pyproject.toml examples/physint-freefall/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip setuptools wheel
	$(BIN)/pip install --quiet "$(TORCH)"
	$(BIN)/pip install --quiet -e ".[dev,ray]" -e examples/physint-freefall
	touch $@

install: $(VENV)/.installed

demo: install
	$(BIN)/physint backends
	$(BIN)/physint pipeline freefall --backend mujoco --preset small --out physint_runs/demo
	$(BIN)/physint view physint_runs/demo/deploy --save physint_runs/demo/deploy.rrd
	@echo "Results: physint_runs/demo/{train,eval,deploy}/artifacts (PNG plots, GIF/MP4 video) and physint_runs/demo/deploy.rrd (rerun)"

test: install
	$(BIN)/python -m pytest -q

benchmark: install
	$(BIN)/python benchmarks/backends.py
	$(BIN)/python benchmarks/memory.py

clean:
	rm -rf $(VENV) physint_runs
