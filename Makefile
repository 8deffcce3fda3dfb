# Every target sets up its own virtual environment from this repository's files
# (pyproject.toml + constraints.txt pin what gets installed), so a fresh machine
# with Python 3.11 only needs `make demo` or `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
PIP    := $(BIN)/python -m pip install --disable-pip-version-check -q -c constraints.txt
export MPLBACKEND ?= Agg

.PHONY: demo test test-all bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.core: pyproject.toml constraints.txt | $(BIN)/python
	$(PIP) -e '.[test]'
	@touch $@

# the peers extra (scipy, numba, casadi) so that every peer of BENCHMARKS.md runs in
# the same `make bench` instead of printing "skipped"
$(VENV)/.bench: $(VENV)/.core
	$(PIP) -e '.[test,bench,peers]'
	@touch $@

demo: $(VENV)/.core
	$(BIN)/nhjax demo

test: $(VENV)/.core
	$(BIN)/python -m pytest

test-all: $(VENV)/.core
	$(BIN)/python -m pytest -m ""

bench: $(VENV)/.bench
	$(BIN)/nhjax bench

clean:
	rm -rf $(VENV) experiments/out benchmarks/out
