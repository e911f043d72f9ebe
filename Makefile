# Two entry points: `make demo` (install + slice a bundled example) and `make test` (install + test suite).
# the first of python3.11, python3.12, python3.13 that runs (a pyenv shim of a version not selected is found but fails),
# else python3; `make PYTHON=/path/to/python3.x` picks another. Only 3.11 to 3.13 are accepted (PY_OK below).
SUPPORTED := 3.11 3.12 3.13
ifeq ($(origin PYTHON),undefined)
PYTHON := $(firstword $(foreach v,$(SUPPORTED),$(shell python$(v) -c 'import sys; print(sys.executable)' 2>/dev/null)) python3)
endif
PY_OK = $(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] in [(3, 11), (3, 12), (3, 13)] else 1)' 2>/dev/null
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= runs/demo

export PREFECT_SERVER_ANALYTICS_ENABLED := false
export DO_NOT_TRACK := 1

.PHONY: install demo test test-fast bench clean

$(STAMP): pyproject.toml constraints.txt
	@$(PY_OK) || { echo "make: $(PYTHON) is $$($(PYTHON) -V 2>/dev/null || echo 'not found'); install Python 3.11 (or 3.12, 3.13) and run make again, or make PYTHON=/path/to/python3.11"; exit 2; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e ".[dev,dask]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/neuralslicer slice neuralslicer/examples/bracket/model.yaml --out $(DEMO_OUT) --max-steps 200 --verify
	@echo "demo results in $(DEMO_OUT): report.md, metrics.json, layers/, field.vtu, model.ply, print.gcode, preview.html"

test: $(STAMP)
	$(BIN)/python -m pytest -q

# the development loop: unit and small integration tests, no end-to-end slice, study or server (what CI runs is `test`)
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) runs .pytest_cache
