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
	$(BIN)/physint pipeline stability --scene all --preset demo --workers 2 --out physint_runs/demo
	@echo "Results under physint_runs/demo/ (ShapeStacks, thesis Chapter 3):"
	@echo "  eval/artifacts/predictions.png        predicted P(falls) on rendered test towers, green where right"
	@echo "  eval/artifacts/occlusion_example.png  where the network looks: occlusion map of an unstable tower"
	@echo "  eval/artifacts/accuracy.png           accuracy by subset, height and violation (Table 3.3), chance 50 %"
	@echo "  train/artifacts/training_curves.png   loss and validation accuracy per epoch"
	@echo "  deploy/artifacts/stackability_*.png   objects ranked by how well they stack (Figs. 3.5, 3.6)"
	@echo "  */metrics.json                        the figures; physint view physint_runs/demo/dataset opens the data"

test: install
	$(BIN)/python -m pytest -q

benchmark: install
	$(BIN)/python benchmarks/backends.py
	$(BIN)/python benchmarks/memory.py

clean:
	rm -rf $(VENV) physint_runs
